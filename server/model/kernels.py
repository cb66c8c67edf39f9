"""numba kernels of the cutting-force model. Arrays in, arrays out; no Python objects inside.

All dot products are taken in the tool frame (e1, e2, e3 = a): the bone-surface normal and the
feed velocity are projected once per call, so each element costs a few dozen flops. Results
are accumulated in the tool frame and rotated to the world frame at the end.

Every material ("how much bone is where each element is going") has one fused kernel per
evaluation that computes its per-element bone fraction and hands it to :func:`accumulate`
(the flat workpiece: ``kernels_flat`` and ``kernels_revolved``; the voxel bone:
``bone.force``).
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel

# Layout of the float64 result vector every material kernel fills (length N_OUT).
OUT_FORCE = 0  # [0:3] force on the burr, world frame, N
OUT_TORQUE = 3  # [3:6] reaction torque about the burr centre, world frame, N·mm
OUT_POWER = 6  # spindle power, N·mm/s (= mW)
OUT_VOLUME_RATE = 7  # removed-volume rate, mm³/s
OUT_COUNT = 8  # number of cutting elements
OUT_CUT_AREA = 9  # burr area in bone and facing the feed, mm²
OUT_SPEED_AREA = 10  # Σ area·|v_t| over the cutting zone, mm²·mm/s
OUT_CONTACT_AREA = 11  # burr area in bone regardless of feed, mm²
OUT_SURFACE_NORMAL = 12  # [12:15] outward bone-surface normal at the cut, world frame
OUT_COMPONENTS = 15  # [15:18] feed, lateral, normal components of the force, N
N_OUT = 18
# The scratch accumulator holds the result's first N_OUT entries while it is summed, then:
ACC_JACOBIAN = N_OUT  # [18:27] ∂F/∂v_f row-major, world frame, N·s/mm (see accumulate_forces)
N_ACC = N_OUT + 9


@hot_kernel
def tool_basis(ax, ay, az):
    """Right-handed orthonormal basis (e1, e2, e3) with e3 = the unit tool axis.

    Branch-free construction of Duff et al. (2017); depends on the axis only, so the result
    does not depend on the burr's roll about its own spin axis. For a = +z it is (x, y, z).
    """
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    ax /= norm
    ay /= norm
    az /= norm
    sign = math.copysign(1.0, az)
    a = -1.0 / (sign + az)
    b = ax * ay * a
    return (
        1.0 + sign * ax * ax * a, sign * b, -sign * ax,
        b, sign + ay * ay * a, -ay,
        ax, ay, az,
    )


@hot_inline
def rotated(c, s, c_step, s_step):
    """(cos, sin) of an angle (c, s) = (cos, sin) turned by a step (c_step, s_step): a
    sub-element's direction from its element's, without a trigonometric call."""
    return c * c_step - s * s_step, s * c_step + c * s_step


@hot_inline
def in_tool_frame(v, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """The vector ``v`` ((3,), grid or world frame) in the tool frame (e1, e2, e3)."""
    return (v[0] * e1x + v[1] * e1y + v[2] * e1z, v[0] * e2x + v[1] * e2y + v[2] * e2z,
            v[0] * e3x + v[1] * e3y + v[2] * e3z)


@hot_kernel
def box_fraction(g0, half_a, half_b):
    """Fraction of a rectangular element where g0 + u + v > 0, u ∈ [−A, A], v ∈ [−B, B].

    This is the exact area fraction of an element whose depth-in-bone is linear across it
    (value g0 at the centre, half-ranges A and B along its two sides): the CDF of the sum of
    two uniform variables, a trapezoid.
    """
    if half_a < half_b:
        half_a, half_b = half_b, half_a
    if g0 <= -(half_a + half_b):
        return 0.0
    if g0 >= half_a + half_b:
        return 1.0
    # In units of the larger half-range, so tiny elements cannot underflow 8·A·B. One
    # division, not two, where 1/A is finite: the carve and the path's share call this
    # ~1 500 times a tick, and divisions queue on one unit.
    if half_a > 1e-300:
        inv_a = 1.0 / half_a
        x = g0 * inv_a
        r = half_b * inv_a
    else:
        x = g0 / half_a
        r = half_b / half_a
    if r <= 1e-12:
        return 0.5 + 0.5 * x
    if x < r - 1.0:
        t = x + 1.0 + r
        return t * t / (8.0 * r)
    if x <= 1.0 - r:
        return 0.5 + 0.5 * x
    t = 1.0 + r - x
    return 1.0 - t * t / (8.0 * r)


@hot_inline
def accumulate_forces(acc, ft, fn, area, vn, st, ct, cp, sp, speed, spin_sign, radius):
    """Add one element's cut to the tool-frame accumulator ``acc`` (shape (N_ACC,)).

    Each element's force is linear in the feed (|Ft_i| ∝ n_i·v_f), so for the elements
    that cut the total force is exactly ``F = J·v_f`` with ``J = Σ f_i n_iᵀ / (n_i·v_f)``;
    ``J`` is accumulated too: the haptic stage integrates the burr proxy implicitly with it.

    Args:
        ft: tangential force magnitude |Ft|, N; fn: normal force magnitude, N (K·|Ft| for a
            single material).
        area: the element's area in bone, mm².
        vn: n·v_f, mm/s, > 0 (the element faces the feed).
        st, ct, cp, sp: sin θ, cos θ, cos φ, sin φ at the element centre.
        speed: |v_t| = |ω|·R·sin θ, mm/s.  spin_sign: sign of ω along a.  radius: R, mm.
    """
    # n = (st cp, st sp, ct), φ̂ = (−sp, cp, 0), θ̂ = (ct cp, ct sp, −st) in the tool frame.
    # F = −|Ft|·sgn·φ̂ − Fn·n;  T = R·n × F = |Ft|·R·sgn·θ̂ (the normal part has no moment).
    f1 = ft * spin_sign * sp - fn * st * cp
    f2 = -(ft * spin_sign * cp + fn * st * sp)
    f3 = -fn * ct
    acc[0] += f1
    acc[1] += f2
    acc[2] += f3
    inv_vn = 1.0 / vn
    n1 = st * cp * inv_vn
    n2 = st * sp * inv_vn
    n3 = ct * inv_vn
    add_jacobian(acc, f1, f2, f3, n1, n2, n3)
    tr = ft * radius * spin_sign
    acc[3] += tr * ct * cp
    acc[4] += tr * ct * sp
    acc[5] -= tr * st
    add_totals(acc, ft, area, vn, speed)


@hot_inline
def add_totals(acc, ft, area, vn, speed):
    """An element's part of the totals in ``acc``: power (|Ft|·|v_t|, N·mm/s), removal rate
    (area·n·v_f, mm³/s), the count of cutting elements, their area (mm²) and Σ area·|v_t|."""
    acc[6] += ft * speed
    acc[7] += area * vn
    acc[8] += 1.0
    acc[9] += area
    acc[10] += area * speed


@hot_inline
def add_jacobian(acc, f1, f2, f3, m1, m2, m3):
    """J += f·mᵀ in ``acc[ACC_JACOBIAN:]`` (row-major 3×3, tool frame): an element's force f
    (N) over its n·v_f, m = n / (n·v_f) (s/mm), so that F = J·v_f over the elements that cut."""
    acc[18] += f1 * m1
    acc[19] += f1 * m2
    acc[20] += f1 * m3
    acc[21] += f2 * m1
    acc[22] += f2 * m2
    acc[23] += f2 * m3
    acc[24] += f3 * m1
    acc[25] += f3 * m2
    acc[26] += f3 * m3


@hot_kernel
def accumulate(acc, frac, vn, st, ct, cp, sp, w_force, w_area, speed, k, spin_sign, radius):
    """One element of a single material (Us folded into ``w_force``).

    Args:
        frac: fraction of the element in bone, [0, 1].
        w_force: Us·R·dθ·dφ/|ω| — the cancelled weight dA/|v_t| times Us, N·s/mm.
        w_area: R²·sin θ·dθ·dφ, the element's area, mm².
        k: normal/tangential ratio; the rest as :func:`accumulate_forces`.
    """
    ft = w_force * vn * frac  # |Ft|, N
    accumulate_forces(acc, ft, k * ft, w_area * frac, vn, st, ct, cp, sp, speed, spin_sign,
                      radius)


@hot_kernel
def rotate_jacobian(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z):
    """J_world = E·J_tool·Eᵀ in place in ``acc[ACC_JACOBIAN:]``, E = [e1 e2 e3] by columns."""
    j = ACC_JACOBIAN
    for r in range(3):  # rows: J_tool·Eᵀ
        a1 = acc[j + 3 * r]
        a2 = acc[j + 3 * r + 1]
        a3 = acc[j + 3 * r + 2]
        acc[j + 3 * r] = a1 * e1x + a2 * e2x + a3 * e3x
        acc[j + 3 * r + 1] = a1 * e1y + a2 * e2y + a3 * e3y
        acc[j + 3 * r + 2] = a1 * e1z + a2 * e2z + a3 * e3z
    for c in range(3):  # columns: E·(J_tool·Eᵀ)
        t1 = acc[j + c]
        t2 = acc[j + 3 + c]
        t3 = acc[j + 6 + c]
        acc[j + c] = e1x * t1 + e2x * t2 + e3x * t3
        acc[j + 3 + c] = e1y * t1 + e2y * t2 + e3y * t3
        acc[j + 6 + c] = e1z * t1 + e2z * t2 + e3z * t3


@hot_kernel
def finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out):
    """Rotate the tool-frame force and torque of ``acc`` to the world frame into ``out`` and
    resolve the force into the thesis's components.

    ``acc[ACC_JACOBIAN:]`` (tool frame) is rotated to the world frame in place.
    ``acc[12:15]`` must hold the outward surface normal ŝ (world frame). As model.md defines
    them: feed = F·f̂ with f̂ = v_f/|v_f|; normal = F·ŝ; lateral = F·(ŝ×f̂) (left of the feed seen
    from outside the bone). Feed and lateral are zero without feed. For a feed in the surface
    the three axes are orthonormal; for a plunging feed they are the thesis's projections.
    """
    for i in range(N_OUT):
        out[i] = acc[i]
    for base in (0, 3):
        a1 = acc[base]
        a2 = acc[base + 1]
        a3 = acc[base + 2]
        out[base] = a1 * e1x + a2 * e2x + a3 * e3x
        out[base + 1] = a1 * e1y + a2 * e2y + a3 * e3y
        out[base + 2] = a1 * e1z + a2 * e2z + a3 * e3z
    rotate_jacobian(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    resolve_components(out[0:3], out[12:15], v_feed, out[15:18])


@hot_kernel
def resolve_components(force, normal, v_feed, out):
    """(feed, lateral, normal) of ``force`` into ``out`` (all float64 (3,)), as model.md
    defines them: feed = F·f̂ with f̂ = v_f/|v_f|; normal = F·ŝ (``normal`` the outward surface
    normal ŝ); lateral = F·(ŝ×f̂). Feed and lateral are zero without feed."""
    fx = force[0]
    fy = force[1]
    fz = force[2]
    sx = normal[0]
    sy = normal[1]
    sz = normal[2]
    out[2] = fx * sx + fy * sy + fz * sz
    speed = math.sqrt(v_feed[0] ** 2 + v_feed[1] ** 2 + v_feed[2] ** 2)
    if speed == 0.0:
        out[0] = 0.0
        out[1] = 0.0
        return
    ux = v_feed[0] / speed
    uy = v_feed[1] / speed
    uz = v_feed[2] / speed
    out[0] = fx * ux + fy * uy + fz * uz
    lx = sy * uz - sz * uy
    ly = sz * ux - sx * uz
    lz = sx * uy - sy * ux
    out[1] = fx * lx + fy * ly + fz * lz


@hot_kernel
def cut_element(acc, frac, st, ct, cp, sp, vu, v3, w_force, w_area, abs_omega, k, spin_sign,
                radius, cutting):
    """Contact area of one element in bone, and its cut if it faces the feed."""
    acc[11] += w_area * frac
    if not cutting:
        return
    vn = st * vu + ct * v3
    if vn > 0.0:
        accumulate(acc, frac, vn, st, ct, cp, sp, w_force, w_area, abs_omega * radius * st, k,
                   spin_sign, radius)


def new_buffer() -> np.ndarray:
    """A zeroed result vector of shape (N_OUT,)."""
    return np.zeros(N_OUT, dtype=np.float64)


def new_scratch() -> np.ndarray:
    """A zeroed accumulator of shape (N_ACC,) (the kernels' ``acc``)."""
    return np.zeros(N_ACC, dtype=np.float64)
