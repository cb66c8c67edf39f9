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
     deep inside bone comes out over several ticks, not in one jump). A burr wholly inside
     bone has no way out to push it along (the engine's ŝ is then the direction of a sum of
     normals that cancel: noise), nor has a shaft sunk past its own axis (its depth stays its
     radius wherever it moves, so the push would never end and would drag the device with
     it): both are left free until part of them is out, as a proxy placed inside an
     obstacle usually is (the burr fades out of the rigid answer from 90 % to 98 % of its
     sphere in bone, not at a threshold). Then nothing pushes against anything, and nothing
     is generated;
   - between the two, across a band of spindle speed above the minimum cutting speed
     (``transition.cut_weight``: s rises from 0 to 1 as a smooth step), the proxy's velocity
     is the blend ``v⁺ = s·v_cut + (1 − s)·v_rigid`` of the two answers to the same free
     velocity. Both are continuous in the state and s is continuous in rpm, so the proxy's
     step and the force the hand feels are too. The blend stays dissipative: each answer has
     a bone force doing no positive work on the proxy, ``(v − v_free)·v ≤ 0`` (the cut's by
     the check below, the rigid projection's with equality), and that set is convex (a ball:
     ``|v − v_free/2| ≤ |v_free|/2``), so their blend is in it; the push-out out of a
     penetration is the one active part, bounded by the penetration, and it acts only below
     the minimum speed: from there on the engine carves what the burr overlaps, and a push
     out of bone the next carve removes anyway would lift the proxy off the surface to fall
     back the tick after (a two-tick cycle), so the rigid answer only stops the proxy. The
     shaft's constraint is linear in v, so it holds for the blend when it holds for both;
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

from ..bone.shaft import SHAFT_DEPTH, SHAFT_FORCE
from ..hot_kernel import hot_kernel
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
    P_SHAFT_RADIUS,
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
#: A burr with at least this share of its sphere in bone counts as wholly inside it; from
#: EMBEDDED_FROM on, its rigid contact fades out toward that.
EMBEDDED_SHARE = 0.98
EMBEDDED_FROM = 0.9


@hot_kernel
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


@hot_kernel
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


@hot_kernel
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


@hot_kernel
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


@hot_kernel
def cut_proxy_velocity(state, params, engine_out, jacobian, radius_mm, embedded, scratch):
    """The proxy's velocity (into state's S_PROXY_V) with the cut treated implicitly:
    ``(A·I − J + dt/h·F·ŝᵀ)·v⁺ = A·v_free`` (module docstring); without the depth term for an
    ``embedded`` burr (no direction makes its cut shallower). ``scratch``: float64 (12,)."""
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
    if area > 0.0 and not embedded and sx * sx + sy * sy + sz * sz > 0.25:
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


@hot_kernel
def push_out(state, nx, ny, nz, depth_mm, params, push_scale=1.0):
    """Constrain the proxy velocity (state's S_PROXY_V) so that a penetration ``depth_mm``
    along the unit outward normal n shrinks to the skin: n·v ≥ rate (× ``push_scale``)."""
    rate = (push_scale * params[P_PUSH_OUT] * max(0.0, depth_mm - params[P_SKIN])
            / state[S_DT])
    g = nx * state[S_PROXY_V] + ny * state[S_PROXY_V + 1] + nz * state[S_PROXY_V + 2]
    if g < rate:
        state[S_PROXY_V] += (rate - g) * nx
        state[S_PROXY_V + 1] += (rate - g) * ny
        state[S_PROXY_V + 2] += (rate - g) * nz


@hot_kernel
def embedded_weight(area_mm2, radius_mm):
    """0 for a burr with at most EMBEDDED_FROM of its sphere in bone, 1 from EMBEDDED_SHARE
    on (wholly inside: no way out), a smooth step between."""
    share = area_mm2 / (4.0 * math.pi * radius_mm * radius_mm)
    if share <= EMBEDDED_FROM:
        return 0.0
    if share >= EMBEDDED_SHARE:
        return 1.0
    u = (share - EMBEDDED_FROM) / (EMBEDDED_SHARE - EMBEDDED_FROM)
    return u * u * (3.0 - 2.0 * u)


@hot_kernel
def rigid_normal(engine_out, radius_mm, embedded):
    """The burr's rigid contact: (nx, ny, nz, depth_mm), the unit outward normal and the
    depth of the cap in bone; depth 0 when there is none, or no way out (``embedded``)."""
    area = engine_out[OUT_CONTACT_AREA]
    if area <= 0.0 or embedded:
        return 0.0, 0.0, 0.0, 0.0
    bx = engine_out[OUT_SURFACE_NORMAL]
    by = engine_out[OUT_SURFACE_NORMAL + 1]
    bz = engine_out[OUT_SURFACE_NORMAL + 2]
    norm = math.sqrt(bx * bx + by * by + bz * bz)
    if norm <= 0.5:
        return 0.0, 0.0, 0.0, 0.0
    return bx / norm, by / norm, bz / norm, area / (2.0 * math.pi * radius_mm)


@hot_kernel
def coupled_finish(state, params, engine_out, jacobian, shaft_out, cut_weight, radius_mm, result,
                   scratch):
    """Step 2 of a coupled tick, after the bone engine ran at the proxy with the free
    velocity: the proxy's implicit step, its contacts, the coupling force, passivity and
    limits.

    Args:
        engine_out: float64 (N_OUT,) the engine's result (``model.kernels.OUT_*``, grid frame).
        jacobian: float64 (9,) ∂F/∂v of the cut (``BoneEngine.jacobian``).
        shaft_out: float64 (N_SHAFT,) the shaft's (``bone.shaft.SHAFT_*``).
        cut_weight: s ∈ [0, 1], the cut's share (``transition.cut_weight``): 0 the bone is a
            rigid obstacle (the spindle is too slow to cut), 1 it is cut.
        radius_mm: the burr's radius.
        result: float64 (N_RESULT,) receives the ``layout.R_*`` values.
        scratch: float64 (12,) work space.

    Returns:
        CLAMPED if a force limit changed the force.
    """
    a = state[S_A]
    dt = state[S_DT]
    s = min(max(cut_weight, 0.0), 1.0)
    f2 = (engine_out[OUT_FORCE] ** 2 + engine_out[OUT_FORCE + 1] ** 2
          + engine_out[OUT_FORCE + 2] ** 2)
    embedded = embedded_weight(engine_out[OUT_CONTACT_AREA], radius_mm) >= 1.0
    # The shaft: always rigid, unless sunk past its axis (module docstring).
    hx = shaft_out[SHAFT_FORCE]
    hy = shaft_out[SHAFT_FORCE + 1]
    hz = shaft_out[SHAFT_FORCE + 2]
    shaft_norm = math.sqrt(hx * hx + hy * hy + hz * hz)
    shaft_depth = shaft_out[SHAFT_DEPTH] if shaft_norm > 0.0 else 0.0
    shaft_r = params[P_SHAFT_RADIUS]
    # Voxel centres within a voxel of the axis: the depth has saturated at the radius.
    if embedded or (shaft_r > 0.0 and shaft_depth >= shaft_r - 2.0 * params[P_DEPTH_FLOOR]):
        shaft_depth = 0.0
    if shaft_depth > 0.0:
        hx /= shaft_norm
        hy /= shaft_norm
        hz /= shaft_norm
    # The cut's answer (the free velocity when nothing cuts), then the shaft on it.
    if s > 0.0 and f2 > 0.0:
        cut_proxy_velocity(state, params, engine_out, jacobian, radius_mm, embedded, scratch)
        state[S_CUT] = 1.0
    else:
        for i in range(3):
            state[S_PROXY_V + i] = state[S_FREE + i]
        state[S_CUT] = 0.0
    # The bone force the cut put on the proxy (its share s of it), and its share of the
    # trial's (power, torque).
    fb2 = 0.0
    for i in range(3):
        fb = s * a * (state[S_PROXY_V + i] - state[S_FREE + i])
        result[R_CUT + i] = fb
        fb2 += fb * fb
    lam = math.sqrt(fb2 / f2) if f2 > 0.0 else 0.0
    if shaft_depth > 0.0:
        push_out(state, hx, hy, hz, shaft_depth, params)
    bx, by, bz, burr_depth = rigid_normal(engine_out, radius_mm, embedded)
    if s < 1.0 and burr_depth > 0.0:
        # The rigid answer to the same free velocity, blended in by 1 − s.
        cut_v = scratch[0:3]
        for i in range(3):
            cut_v[i] = state[S_PROXY_V + i]
            state[S_PROXY_V + i] = state[S_FREE + i]
        # Where the engine carves, the bone a penetration reaches is gone the next tick: a
        # push out of it would lift the proxy off the surface, let it fall back the tick
        # after, and so on (a two-tick cycle); the rigid answer then only stops the proxy.
        push = 1.0 if s <= 0.0 and f2 <= 0.0 else 0.0
        for _ in range(4):  # Gauss–Seidel over the two constraints
            push_out(state, bx, by, bz, burr_depth, params, push)
            if shaft_depth > 0.0:
                push_out(state, hx, hy, hz, shaft_depth, params)
        # A burr almost wholly in bone fades out of the rigid answer, not at a threshold.
        e = embedded_weight(engine_out[OUT_CONTACT_AREA], radius_mm)
        for i in range(3):
            rigid = e * cut_v[i] + (1.0 - e) * state[S_PROXY_V + i]
            state[S_PROXY_V + i] = s * cut_v[i] + (1.0 - s) * rigid
    k = state[S_K]
    b = state[S_B]
    force = result[R_FORCE:R_FORCE + 3]
    for i in range(3):
        state[S_PROXY + i] += state[S_PROXY_V + i] * dt
        force[i] = (k * (state[S_PROXY + i] - state[S_DEVICE + i])
                    + b * (state[S_PROXY_V + i] - state[S_DEVICE_V + i]))
    energy = state[S_ENERGY]
    # Limits the API accepts (a stiffness or damping of 1e-300) on a slow stream take k to
    # 0: a spring that holds nothing, whose cap is unbounded.
    cap = 0.5 * params[P_MAX_FORCE] ** 2 / k if k > 0.0 else math.inf
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


@hot_kernel
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
