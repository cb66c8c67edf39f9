"""The coupled output: a burr proxy integrated implicitly, tied to the device by a virtual
coupling (Adams & Hannaford's spring-damper). numba kernels on the layout of ``layout.py``.

Each tick, around the one bone-engine call:

1. :func:`coupled_predict` — where the proxy would go without bone: backward Euler of the
   proxy (mass m) pulled by the coupling spring k and damper b toward the device,
   ``(m/dt + k·dt + b)·v_free = m/dt·v + k·(x_dev − x) + b·v_dev``. The bone engine then
   cuts at the proxy's position with a predicted velocity as the feed.
2. :func:`coupled_finish` — the bone's answer enters the same implicit step:
   - for the elements that cut, the cutting force is exactly linear in the feed, F = J·v
     (model.md: |Ft_i| ∝ n_i·v_f; the force kernels accumulate J), and it weakens as the
     proxy leaves the bone along the surface normal ŝ (h the depth of cut: a sphere cap of
     area a is a/2πR deep). The step solves ``(A·I − J + dt/h·F·ŝᵀ)·v⁺ = A·v_free`` with
     A = m/dt + k·dt + b. For a dissipative cut |v⁺| ≤ |v_free| whatever Us, K or rpm (the
     explicit step needs β·dt/m < 2: ~10⁴ times too small here); a solution in which the
     bone would push the proxy along its motion falls back to an isotropic damper;
   - what does not cut is a rigid obstacle: the burr below the minimum cutting speed and the
     shaft always. A penetration deeper than the contact skin is pushed out along the
     surface normal (a velocity constraint, a fraction of it per tick so that a burr placed
     deep inside bone comes out over several ticks, not in one jump);
   - the force for the hand is the coupling's, ``k·(x_proxy − x_dev) + b·(v_proxy − v_dev)``,
     then the passivity controller, the force clamp and the slew limit.

The coupling follows the packet rate: Colgate's condition b_device > k·T/2 + b means a device
updated every T holds at most a stiffness ∝ 1/T, and a sampled damper needs b·T/m < 2. With
r = min(1, rated period / T) the damping budget is r·b_max: b = r·b_max/2 and
k = min(r·k_rated, r·b_max/T).

Units: mm, s, N (stiffness N/mm, damping N·s/mm, mass N·s²/mm).
"""

from __future__ import annotations

import math

from numba import njit

from ..bone.shaft import SHAFT_DEPTH, SHAFT_FORCE
from ..model.kernels import (
    OUT_CONTACT_AREA,
    OUT_FORCE,
    OUT_SURFACE_NORMAL,
    resolve_components,
)
from .layout import (
    P_DEPTH_FLOOR,
    P_MAX_DAMPING,
    P_MAX_FORCE,
    P_MAX_SLEW,
    P_MAX_SPEED,
    P_MAX_STIFFNESS,
    P_PERIOD_GAIN,
    P_PROXY_MASS,
    P_PUSH_OUT,
    P_RATED_PERIOD,
    P_SKIN,
    P_TRIAL_RELAX,
    R_B,
    R_COMPONENTS,
    R_CUT,
    R_CUT_SCALE,
    R_ENERGY,
    R_FORCE,
    R_K,
    R_PC_DAMPING,
    R_PROXY,
    R_PROXY_V,
    S_A,
    S_B,
    S_CUT,
    S_DEVICE,
    S_DEVICE_PREV,
    S_DEVICE_V,
    S_DT,
    S_ENERGY,
    S_FORCE,
    S_FREE,
    S_HAVE_PREV,
    S_K,
    S_PERIOD,
    S_PROXY,
    S_PROXY_V,
    S_READY,
    S_TRIAL,
)
from .limits import limit_force
from .passivity import control, observe

#: Bits of the predict/finish return values.
PLACED = 1  # the proxy was (re)placed at the device: the engine must forget its last carve
CLAMPED = 2  # a force limit changed the force


@njit(cache=True, nogil=True)
def track_period(state, params, dt_s):
    """Smooth the packet interval and set the coupling's stiffness and damping from it."""
    period = state[S_PERIOD]
    period = dt_s if period <= 0.0 else period + params[P_PERIOD_GAIN] * (dt_s - period)
    state[S_PERIOD] = period
    # A sampled damper is bounded like the spring (b·T/m < 2 on the device's mass): both
    # scale with the rated period over the actual one.
    rate = min(1.0, params[P_RATED_PERIOD] / period)
    b_max = params[P_MAX_DAMPING] * rate
    k_max = params[P_MAX_STIFFNESS]
    state[S_K] = min(k_max * rate, b_max / period)
    state[S_B] = 0.5 * b_max


@njit(cache=True, nogil=True)
def place_proxy(state, device_p):
    """Put the proxy on the device, at rest, and restart the passivity observer."""
    for i in range(3):
        state[S_PROXY + i] = device_p[i]
        state[S_PROXY_V + i] = 0.0
        state[S_FREE + i] = 0.0
    state[S_READY] = 1.0
    state[S_CUT] = 0.0
    state[S_ENERGY] = 0.0
    state[S_HAVE_PREV] = 0.0


@njit(cache=True, nogil=True)
def coupled_predict(state, params, device_p, device_v, dt_s, place, centre_out, feed_out):
    """Step 1 of a coupled tick: the proxy's free velocity, and the velocity the bone engine
    evaluates the cut at.

    Which elements cut depends on the feed's direction, so the engine must see a good guess
    of the proxy's next velocity: while the bone cut the proxy last tick, its last velocity
    (pulled through bone, the free velocity points mostly where the coupling spring is
    stretched, into the bone; the proxy moves along the cut), else the free velocity;
    relaxed toward that guess by ``P_TRIAL_RELAX`` per tick (a whole step would let the
    proxy alternate between a cutting and a free tick).

    Args:
        state: float64 (N_STATE,); params: float64 (N_PARAMS,).
        device_p: (3,) device (burr) position, grid frame, mm.  device_v: (3,) its velocity
            estimate, mm/s.  dt_s: the interval since the last tick (client clock), s, > 0.
        place: put the proxy on the device first (a new stream, a teleport, a reset).
        centre_out, feed_out: (3,) receive where the bone engine must cut (the proxy) and
            the feed velocity to evaluate, mm and mm/s.

    Returns:
        PLACED if the proxy was placed on the device (also when its free velocity exceeded
        the speed limit: a jump of the device is not a cut).
    """
    flags = 0
    track_period(state, params, dt_s)
    if place or state[S_READY] == 0.0:
        place_proxy(state, device_p)
        flags |= PLACED
    k = state[S_K]
    b = state[S_B]
    m_dt = params[P_PROXY_MASS] / dt_s
    a = m_dt + k * dt_s + b
    speed2 = 0.0
    for i in range(3):
        vf = (m_dt * state[S_PROXY_V + i] + k * (device_p[i] - state[S_PROXY + i])
              + b * device_v[i]) / a
        state[S_FREE + i] = vf
        speed2 += vf * vf
    if speed2 > params[P_MAX_SPEED] ** 2:
        place_proxy(state, device_p)
        flags |= PLACED
        for i in range(3):
            state[S_FREE + i] = b * device_v[i] / a
    cut = state[S_CUT] != 0.0
    relax = params[P_TRIAL_RELAX] if flags == 0 else 1.0
    state[S_A] = a
    state[S_DT] = dt_s
    for i in range(3):
        guess = state[S_PROXY_V + i] if cut else state[S_FREE + i]
        state[S_TRIAL + i] += relax * (guess - state[S_TRIAL + i])
        state[S_DEVICE + i] = device_p[i]
        state[S_DEVICE_V + i] = device_v[i]
        centre_out[i] = state[S_PROXY + i]
        feed_out[i] = state[S_TRIAL + i]
    return flags


@njit(cache=True, nogil=True)
def solve3(m, rhs, out):
    """out = m⁻¹·rhs for a 3×3 ``m`` (row-major (9,)) by Cramer's rule; False if singular."""
    c0 = m[4] * m[8] - m[5] * m[7]
    c1 = m[5] * m[6] - m[3] * m[8]
    c2 = m[3] * m[7] - m[4] * m[6]
    det = m[0] * c0 + m[1] * c1 + m[2] * c2
    scale = max(abs(m[0]), abs(m[4]), abs(m[8])) ** 3
    if not abs(det) > 1e-12 * scale:  # also catches NaN
        return False
    inv = 1.0 / det
    r0 = rhs[0]
    r1 = rhs[1]
    r2 = rhs[2]
    out[0] = (c0 * r0 + (m[2] * m[7] - m[1] * m[8]) * r1 + (m[1] * m[5] - m[2] * m[4]) * r2) * inv
    out[1] = (c1 * r0 + (m[0] * m[8] - m[2] * m[6]) * r1 + (m[2] * m[3] - m[0] * m[5]) * r2) * inv
    out[2] = (c2 * r0 + (m[1] * m[6] - m[0] * m[7]) * r1 + (m[0] * m[4] - m[1] * m[3]) * r2) * inv
    return True


@njit(cache=True, nogil=True)
def cut_proxy_velocity(state, params, engine_out, jacobian, radius_mm, scratch):
    """The proxy's velocity (into state's S_PROXY_V) with the cut treated implicitly:
    ``(A·I − J + dt/h·F·ŝᵀ)·v⁺ = A·v_free`` (module docstring). ``scratch``: float64 (12,)."""
    a = state[S_A]
    dt = state[S_DT]
    m = scratch[0:9]
    for i in range(9):
        m[i] = -jacobian[i]
    m[0] += a
    m[4] += a
    m[8] += a
    sx = engine_out[OUT_SURFACE_NORMAL]
    sy = engine_out[OUT_SURFACE_NORMAL + 1]
    sz = engine_out[OUT_SURFACE_NORMAL + 2]
    area = engine_out[OUT_CONTACT_AREA]
    if area > 0.0 and sx * sx + sy * sy + sz * sz > 0.25:
        # Leaving the bone along ŝ makes the cut shallower, and the force with it.
        w = dt / max(area / (2.0 * math.pi * radius_mm), params[P_DEPTH_FLOOR])
        for r in range(3):
            f = engine_out[OUT_FORCE + r] * w
            m[3 * r] += f * sx
            m[3 * r + 1] += f * sy
            m[3 * r + 2] += f * sz
    rhs = scratch[9:12]
    for i in range(3):
        rhs[i] = a * state[S_FREE + i]
    v = state[S_PROXY_V:S_PROXY_V + 3]
    solved = solve3(m, rhs, v)
    if solved:
        # The bone must not drive the proxy: the spindle's tangential forces can push along
        # the motion (a burr "walking"), energy the device would receive from nowhere.
        work = 0.0
        for i in range(3):
            work += (v[i] - state[S_FREE + i]) * v[i]
        solved = work <= 0.0
    if not solved:
        # A degenerate or active linearization: the cut as an isotropic damper of the same
        # strength, dissipative by construction.
        f2 = 0.0
        t2 = 0.0
        for i in range(3):
            f2 += engine_out[OUT_FORCE + i] ** 2
            t2 += state[S_TRIAL + i] ** 2
        beta = math.sqrt(f2 / t2) if t2 > 0.0 else 0.0
        for i in range(3):
            v[i] = a * state[S_FREE + i] / (a + beta)


@njit(cache=True, nogil=True)
def push_out(state, nx, ny, nz, depth_mm, params):
    """Constrain the proxy velocity (state's S_PROXY_V) so that a penetration ``depth_mm``
    along the unit outward normal n shrinks to the skin: n·v ≥ rate."""
    rate = params[P_PUSH_OUT] * max(0.0, depth_mm - params[P_SKIN]) / state[S_DT]
    g = nx * state[S_PROXY_V] + ny * state[S_PROXY_V + 1] + nz * state[S_PROXY_V + 2]
    if g < rate:
        state[S_PROXY_V] += (rate - g) * nx
        state[S_PROXY_V + 1] += (rate - g) * ny
        state[S_PROXY_V + 2] += (rate - g) * nz


@njit(cache=True, nogil=True)
def coupled_finish(state, params, engine_out, jacobian, shaft_out, cutting, radius_mm, result,
                   scratch):
    """Step 2 of a coupled tick, after the bone engine ran at the proxy with the free
    velocity: the proxy's implicit step, its contacts, the coupling force, passivity and
    limits.

    Args:
        engine_out: float64 (N_OUT,) the engine's result (``model.kernels.OUT_*``, grid frame).
        jacobian: float64 (9,) ∂F/∂v of the cut (``BoneEngine.jacobian``).
        shaft_out: float64 (N_SHAFT,) the shaft's (``bone.shaft.SHAFT_*``).
        cutting: the spindle turns fast enough to cut (else the bone is a rigid obstacle).
        radius_mm: the burr's radius.
        result: float64 (N_RESULT,) receives the ``layout.R_*`` values.
        scratch: float64 (12,) work space.

    Returns:
        CLAMPED if a force limit changed the force.
    """
    a = state[S_A]
    dt = state[S_DT]
    f2 = (engine_out[OUT_FORCE] ** 2 + engine_out[OUT_FORCE + 1] ** 2
          + engine_out[OUT_FORCE + 2] ** 2)
    if cutting and f2 > 0.0:
        cut_proxy_velocity(state, params, engine_out, jacobian, radius_mm, scratch)
        state[S_CUT] = 1.0
    else:
        for i in range(3):
            state[S_PROXY_V + i] = state[S_FREE + i]
        state[S_CUT] = 0.0
    # The force the bone put on the proxy, and its share of the trial's (power, torque).
    fb2 = 0.0
    for i in range(3):
        fb = a * (state[S_PROXY_V + i] - state[S_FREE + i])
        result[R_CUT + i] = fb
        fb2 += fb * fb
    lam = math.sqrt(fb2 / f2) if f2 > 0.0 else 0.0
    # Rigid contacts: the burr when it does not cut, the shaft always.
    bx = by = bz = burr_depth = 0.0
    area = engine_out[OUT_CONTACT_AREA]
    if not cutting and area > 0.0:
        bx = engine_out[OUT_SURFACE_NORMAL]
        by = engine_out[OUT_SURFACE_NORMAL + 1]
        bz = engine_out[OUT_SURFACE_NORMAL + 2]
        norm = math.sqrt(bx * bx + by * by + bz * bz)
        if norm > 0.5:  # an embedded burr has no outward direction: left free
            bx /= norm
            by /= norm
            bz /= norm
            burr_depth = area / (2.0 * math.pi * radius_mm)
    hx = shaft_out[SHAFT_FORCE]
    hy = shaft_out[SHAFT_FORCE + 1]
    hz = shaft_out[SHAFT_FORCE + 2]
    shaft_norm = math.sqrt(hx * hx + hy * hy + hz * hz)
    shaft_depth = shaft_out[SHAFT_DEPTH] if shaft_norm > 0.0 else 0.0
    if shaft_norm > 0.0:
        hx /= shaft_norm
        hy /= shaft_norm
        hz /= shaft_norm
    if burr_depth > 0.0 or shaft_depth > 0.0:
        for _ in range(4):  # Gauss–Seidel over the two constraints
            if burr_depth > 0.0:
                push_out(state, bx, by, bz, burr_depth, params)
            if shaft_depth > 0.0:
                push_out(state, hx, hy, hz, shaft_depth, params)
    k = state[S_K]
    b = state[S_B]
    force = result[R_FORCE:R_FORCE + 3]
    for i in range(3):
        state[S_PROXY + i] += state[S_PROXY_V + i] * dt
        force[i] = (k * (state[S_PROXY + i] - state[S_DEVICE + i])
                    + b * (state[S_PROXY_V + i] - state[S_DEVICE_V + i]))
    energy = state[S_ENERGY]
    cap = 0.5 * params[P_MAX_FORCE] ** 2 / k
    if state[S_HAVE_PREV] != 0.0:
        dx = result[R_PROXY:R_PROXY + 3]  # scratch until the proxy is written below
        for i in range(3):
            dx[i] = state[S_DEVICE + i] - state[S_DEVICE_PREV + i]
        energy = observe(energy, state[S_FORCE:S_FORCE + 3], dx, cap)
    alpha = control(energy, force, state[S_DEVICE_V:S_DEVICE_V + 3], dt, 2.0 * state[S_B])
    flags = 0
    if limit_force(force, state[S_FORCE:S_FORCE + 3], params[P_MAX_FORCE],
                   params[P_MAX_SLEW] * dt):
        flags |= CLAMPED
    state[S_ENERGY] = energy
    state[S_HAVE_PREV] = 1.0
    for i in range(3):
        state[S_FORCE + i] = force[i]
        state[S_DEVICE_PREV + i] = state[S_DEVICE + i]
        result[R_PROXY + i] = state[S_PROXY + i]
        result[R_PROXY_V + i] = state[S_PROXY_V + i]
    result[R_CUT_SCALE] = lam
    # The cut the proxy met as model.md's components, about the proxy's velocity.
    resolve_components(result[R_CUT:R_CUT + 3],
                       engine_out[OUT_SURFACE_NORMAL:OUT_SURFACE_NORMAL + 3],
                       state[S_PROXY_V:S_PROXY_V + 3], result[R_COMPONENTS:R_COMPONENTS + 3])
    result[R_PC_DAMPING] = alpha
    result[R_K] = k
    result[R_B] = b
    result[R_ENERGY] = energy
    return flags


@njit(cache=True, nogil=True)
def raw_limits(state, params, force, dt_s):
    """The raw output on a device: the model's force (float64 (3,), N, grid frame, in place)
    clamped and slew-limited, nothing else. Returns CLAMPED if a limit acted."""
    flags = 0
    if limit_force(force, state[S_FORCE:S_FORCE + 3], params[P_MAX_FORCE],
                   params[P_MAX_SLEW] * dt_s):
        flags |= CLAMPED
    for i in range(3):
        state[S_FORCE + i] = force[i]
    return flags
