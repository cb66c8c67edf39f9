"""numba kernels of the round burr on the flat workpiece (``model.workpiece``): the bone is the
half-space below a plane, each element's bone fraction its linearized depth over its extent
(a box fraction), refined on sub-elements where the surface crosses it, and a cut cap a few
elements across integrated exactly (``cut_cap``). The element sums, the layout of the result
and the rotation to the world frame are ``kernels``' (shared with the voxel bone).
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_kernel
from .kernels import (
    ACC_JACOBIAN,
    N_ACC,
    N_OUT,
    box_fraction,
    cut_element,
    finish,
    in_tool_frame,
    rotated,
    tool_basis,
)

#: The small-cap integral (:func:`cut_cap`) integrates latitudes by Gauss–Legendre on these
#: nodes between breakpoints; the longitudes are integrated in closed form.
CAP_GL_X, CAP_GL_W = np.polynomial.legendre.leggauss(8)
#: A cut cap narrower than this many elements (angular radius in units of dθ) is integrated
#: exactly by :func:`cut_cap` instead of on the burr grid, whose linearized fractions and
#: centre-point integrand fail where the cap is a few elements across (where the depth peaks
#: inside one element: removal ×144 at the pole 1 nm deep, +4.7 % at 10 µm).
CAP_GRID_ELEMENTS = 4.0
#: ... and at most this angular radius, rad (0.25 mm deep with R = 2 mm): the thesis's cuts
#: (0.5 mm deep) stay on the grid at any resolution. The grid is then within about 1 %.
CAP_GRID_MAX_RAD = 0.5
#: Over the last fifth of that radius the two are blended smoothly: a switch would step by
#: the grid's error, and a step down breaks force against depth being monotone.
CAP_BLEND = 0.2
#: A refined element is shifted toward its centre-point value over the last part of its
#: filling, from this mean bone fraction on (see :func:`flat_grid`).
WHOLE_FROM = 0.75


@hot_kernel
def add_removal_correction(acc, dv, us, abs_omega, spin_sign):
    """Move an element's removal rate by ``dv`` (mm³/s) from its midpoint value toward its
    exact integral over the element, in the tool-frame ``acc``; the spindle power (Us·dv) and
    the reaction torque along the axis (−sgn(ω)·Us·dv/|ω|) move with it, so P = Us × removal
    and P = −T·Ω stay exact. The force keeps the midpoint rule, whose error is smaller: its
    weight dA/|v_t| has no ρ, and ρ·(n·v_f) is what curves near a pole and across a rim."""
    acc[7] += dv
    acc[6] += us * dv
    acc[5] -= spin_sign * us * dv / abs_omega


@hot_kernel
def facing_share(vn, vary):
    """How much of an element's removal correction applies: 1 where n·v_f (``vn`` at its
    centre, mm/s) keeps its sign across it (varies by less than ``vary``), falling smoothly to 0
    at vn = 0, where the exact integral would count the part facing away, and the element
    leaves the cut without a step."""
    if vn >= vary:
        return 1.0
    if vn <= 0.0:
        return 0.0
    x = vn / vary
    return x * x * (3.0 - 2.0 * x)


@hot_kernel
def positive_mean(x, half_a, half_b):
    """E[max(x + u + v, 0)] for u, v uniform on [−A, A] and [−B, B]: the mean over an element
    of the positive part of a quantity linear across it (``x`` at its centre, half-ranges A and
    B). Its derivative in x is ``box_fraction``; it tends to max(x, 0) as the element shrinks.
    """
    if half_a < half_b:
        half_a, half_b = half_b, half_a
    reach = half_a + half_b
    if x >= reach:
        return x
    if x <= -reach:
        return 0.0
    # G(x) = x + G(−x): the lower half, in units of A (|x| < 2A here, so tiny elements
    # cannot underflow A·B, as in box_fraction).
    y = -abs(x) / half_a
    r = half_b / half_a
    if r <= 1e-12:
        low = 0.25 * (y + 1.0) ** 2
    elif y <= r - 1.0:
        low = (y + 1.0 + r) ** 3 / (24.0 * r)
    else:
        low = r * r / 3.0 + 0.5 * (y + 1.0 - r) + 0.25 * (y * y - (1.0 - r) ** 2)
    low *= half_a
    return low + x if x > 0.0 else low


@hot_kernel
def arc_moments(centre, half):
    """∫ of (1, cos φ, sin φ, cos²φ, sin²φ, cos φ·sin φ) dφ over [centre − half, centre + half]."""
    c2 = math.cos(2.0 * centre)
    s2 = math.sin(2.0 * centre)
    sh = math.sin(half)
    sh2 = math.sin(2.0 * half)
    return (2.0 * half, 2.0 * math.cos(centre) * sh, 2.0 * math.sin(centre) * sh,
            half + 0.5 * c2 * sh2, half - 0.5 * c2 * sh2, 0.5 * s2 * sh2)


@hot_kernel
def arcs_moments(ca, ha, cb, hb):
    """:func:`arc_moments` summed over the intersection of two arcs (centre, half-width ≤ π,
    rad): up to two pieces."""
    la = 2.0 * ha
    lb = 2.0 * hb
    a0 = ca - ha
    d = (cb - hb - a0) % (2.0 * math.pi)
    m0 = mc = ms = mcc = mss = mcs = 0.0
    if d < la:
        hi = min(d + lb, la)
        m0, mc, ms, mcc, mss, mcs = arc_moments(a0 + 0.5 * (d + hi), 0.5 * (hi - d))
    wrap = d + lb - 2.0 * math.pi
    if wrap > 0.0:
        hi = min(wrap, la)
        n0, nc, ns, ncc, nss, ncs = arc_moments(a0 + 0.5 * hi, 0.5 * hi)
        m0 += n0
        mc += nc
        ms += ns
        mcc += ncc
        mss += nss
        mcs += ncs
    return m0, mc, ms, mcc, mss, mcs


@hot_kernel
def _polar(x, y, z):
    """Polar angle from e3 of the tool-frame direction (x, y, z), rad; −1 for a zero vector."""
    rho = math.sqrt(x * x + y * y)
    if rho == 0.0 and z == 0.0:
        return -1.0
    return math.atan2(rho, z)


@hot_kernel
def cut_cap(s1, s2, s3, v1, v2, v3, depth, radius, abs_omega, spin_sign, us, k, weight, acc):
    """The cut of the cap ``depth`` mm deep that a flat surface takes from the burr, integrated
    exactly, added ×``weight`` to the tool-frame accumulator ``acc`` (shape (N_ACC,)).

    (s1, s2, s3): unit outward surface normal, (v1, v2, v3): feed, mm/s, both in the tool
    frame. On each latitude θ the bone (an arc of longitudes about the cap's centre −s) and
    the part facing the feed (an arc about the feed's azimuth) are closed-form, and every
    integrand of ``accumulate_forces`` is a trigonometric polynomial of degree 2 in φ, so the
    longitudes are integrated exactly over their intersection; the latitudes by Gauss–Legendre
    between the latitudes where that arc structure changes (sine-substituted, which absorbs
    the square-root ends where a latitude grazes the cap). Only the contact area and the
    force's weight dA/|v_t| = R·dθ·dφ/ω are used, so the spin pole needs no care. All
    breakpoints move continuously with the pose, so the result does too.

    Returns the (θ, φ) measure of the cutting region, rad² (×``weight``), from which the
    caller estimates an element count.
    """
    cap_half = 2.0 * math.asin(math.sqrt(min(max(depth, 0.0) / (2.0 * radius), 1.0)))
    # The cap's centre −s at polar angle θc and azimuth ψc.
    sin_c = math.sqrt(s1 * s1 + s2 * s2)
    theta_c = math.atan2(sin_c, -s3)
    psi_c = math.atan2(-s2, -s1)
    v_perp = math.sqrt(v1 * v1 + v2 * v2)
    psi_v = math.atan2(v2, v1)
    lo = max(theta_c - cap_half, 0.0)
    hi = min(theta_c + cap_half, math.pi)
    # Latitudes where the arcs change form: the cap's extreme ones (or where it starts
    # holding whole latitude circles around a pole), the feed's great circle's extreme ones,
    # its crossings of the cap's rim and its point nearest the cap's centre (where crossings
    # are born as the cap grows, so they split no interval suddenly).
    b1 = abs(theta_c - cap_half)
    b2 = math.pi - abs(math.pi - theta_c - cap_half)
    b3 = math.atan2(abs(v3), v_perp)
    b4 = math.pi - b3
    b5 = -1.0
    b6 = -1.0
    b7 = -1.0
    speed = math.sqrt(v_perp * v_perp + v3 * v3)
    if speed > 0.0:
        f1 = v1 / speed
        f2 = v2 / speed
        f3 = v3 / speed
        cos_sv = s1 * f1 + s2 * f2 + s3 * f3
        b7 = _polar(-s1 + cos_sv * f1, -s2 + cos_sv * f2, -s3 + cos_sv * f3)
        sin2 = 1.0 - cos_sv * cos_sv
        if sin2 > 1e-12:
            level = -math.cos(cap_half)  # the rim: s·n = level, and v·n = 0
            x = level / sin2
            y = -cos_sv * level / sin2
            z2 = 1.0 - (x * x + y * y + 2.0 * x * y * cos_sv)
            if z2 > 0.0:
                z = math.sqrt(z2 / sin2)
                w1 = s2 * f3 - s3 * f2
                w2 = s3 * f1 - s1 * f3
                w3 = s1 * f2 - s2 * f1
                px = x * s1 + y * f1
                py = x * s2 + y * f2
                pz = x * s3 + y * f3
                b5 = _polar(px + z * w1, py + z * w2, pz + z * w3)
                b6 = _polar(px - z * w1, py - z * w2, pz - z * w3)
    breaks = (b1, b2, b3, b4, b5, b6, b7)
    w_force = us * radius / abs_omega * weight  # Us·dA/|v_t| per dθ·dφ, N·s/mm
    r2 = radius * radius * weight
    measure = 0.0
    t = lo
    while t < hi:
        nxt = hi
        for b in breaks:
            if t < b < nxt:
                nxt = b
        mid = 0.5 * (t + nxt)
        half = 0.5 * (nxt - t)
        for i in range(CAP_GL_X.shape[0]):
            u = 0.5 * math.pi * CAP_GL_X[i]
            th = mid + half * math.sin(u)
            wq = 0.5 * math.pi * CAP_GL_W[i] * half * math.cos(u)
            st = math.sin(th)
            ct = math.cos(th)
            # In bone: sin²(Δφ/2) < (sin²(β/2) − sin²((θ − θc)/2)) / (sin θ sin θc).
            num = math.sin(0.5 * (cap_half - th + theta_c)) * math.sin(
                0.5 * (cap_half + th - theta_c))
            if num <= 0.0:
                continue
            den = st * sin_c
            half_bone = math.pi if num >= den else 2.0 * math.asin(math.sqrt(num / den))
            # Facing the feed: v⊥·sin θ·cos(φ − ψv) > −v3·cos θ.
            lead = ct * v3
            reach = v_perp * st
            if lead <= -reach:
                continue
            half_face = math.pi if lead >= reach else math.acos(-lead / reach)
            m0, mc, ms, mcc, mss, mcs = arcs_moments(psi_c, half_bone, psi_v, half_face)
            if m0 <= 0.0:
                continue
            # ∫ n·v_f, ∫ (n·v_f) cos φ, ∫ (n·v_f) sin φ over the arcs.
            vn0 = st * (v1 * mc + v2 * ms) + ct * v3 * m0
            vnc = st * (v1 * mcc + v2 * mcs) + ct * v3 * mc
            vns = st * (v1 * mcs + v2 * mss) + ct * v3 * ms
            wf = wq * w_force
            acc[0] += wf * (spin_sign * vns - k * st * vnc)
            acc[1] -= wf * (spin_sign * vnc + k * st * vns)
            acc[2] -= wf * k * ct * vn0
            tr = wf * radius * spin_sign
            acc[3] += tr * ct * vnc
            acc[4] += tr * ct * vns
            acc[5] -= tr * st * vn0
            acc[6] += wf * abs_omega * radius * st * vn0
            acc[7] += wq * r2 * st * vn0
            acc[9] += wq * r2 * st * m0
            acc[10] += wq * r2 * st * m0 * abs_omega * radius * st
            acc[18] += wf * st * (spin_sign * mcs - k * st * mcc)
            acc[19] += wf * st * (spin_sign * mss - k * st * mcs)
            acc[20] += wf * ct * (spin_sign * ms - k * st * mc)
            acc[21] -= wf * st * (spin_sign * mcc + k * st * mcs)
            acc[22] -= wf * st * (spin_sign * mcs + k * st * mss)
            acc[23] -= wf * ct * (spin_sign * mc + k * st * ms)
            acc[24] -= wf * k * ct * st * mc
            acc[25] -= wf * k * ct * st * ms
            acc[26] -= wf * k * ct * ct * m0
            measure += wq * m0 * weight
        t = nxt
    return measure


@hot_kernel
def start_flat(centre, axis, v_feed, plane_point, plane_normal, acc, out):
    """Common start of the flat-workpiece kernels: zero ``acc`` (N_ACC,) and ``out``
    (N_OUT,), put the surface normal in both (it is the bone's normal everywhere).

    Returns (d0, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, s1, s2, s3, v1, v2, v3): the
    surface's depth below ``centre`` along the inward normal, mm; the tool basis
    (``tool_basis``); the outward normal and the feed (mm/s) in the tool frame.
    """
    for i in range(N_ACC):
        acc[i] = 0.0
    for i in range(N_OUT):
        out[i] = 0.0
    sx = plane_normal[0]
    sy = plane_normal[1]
    sz = plane_normal[2]
    acc[12] = sx
    acc[13] = sy
    acc[14] = sz
    out[12] = sx
    out[13] = sy
    out[14] = sz
    d0 = (sx * (plane_point[0] - centre[0]) + sy * (plane_point[1] - centre[1])
          + sz * (plane_point[2] - centre[2]))
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = tool_basis(axis[0], axis[1], axis[2])
    s1 = sx * e1x + sy * e1y + sz * e1z
    s2 = sx * e2x + sy * e2y + sz * e2z
    s3 = sx * e3x + sy * e3y + sz * e3z
    v1, v2, v3 = in_tool_frame(v_feed, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    return d0, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, s1, s2, s3, v1, v2, v3


@hot_kernel
def cut_flat(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
             sin_sub_p, radius, centre, axis, v_feed, omega, us, k, cutting, plane_point,
             plane_normal, acc, out):
    """Cutting force of a spherical burr against a flat bone half-space. One call per evaluation.

    A cut cap narrower than ``CAP_GRID_ELEMENTS`` elements (at most ``CAP_GRID_MAX_RAD``) is
    integrated exactly (:func:`cut_cap`), a wider one on the burr grid (:func:`flat_grid`),
    blended smoothly in between.

    Args:
        cos_t, sin_t: (n_theta,) band-midpoint tables; cos_p, sin_p: (n_phi,) sector tables.
        d_theta, d_phi: element extents, rad.
        cos_sub_t, sin_sub_t, cos_sub_p, sin_sub_p: (m,) offsets of the m×m sub-elements an
            element is split into when the bone surface crosses it (m = 1: no split).
        radius: R, mm.  centre: (3,) burr centre, mm.
        axis: (3,) tool axis toward the handle (any length > 0).
        v_feed: (3,) velocity of the burr centre relative to the bone, mm/s.
        omega: signed spindle speed along the axis, rad/s (Ω = omega·a; forward is negative).
        us: Us, N/mm².  k: K.  cutting: False below the minimum cutting speed (contact only).
        plane_point: (3,) a point on the bone surface, mm.
        plane_normal: (3,) unit outward surface normal; bone lies on the other side.
        acc: (N_ACC,) scratch; out: (N_OUT,) result, laid out as the OUT_* constants.
    """
    # g = d0 − R·(s·n) is how deep an element centre lies in bone (positive inside).
    (d0, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, s1, s2, s3, v1, v2,
     v3) = start_flat(centre, axis, v_feed, plane_point, plane_normal, acc, out)
    if d0 <= -radius:  # the whole burr is outside the bone
        return
    abs_omega = abs(omega)
    spin_sign = 1.0 if omega >= 0.0 else -1.0
    depth = d0 + radius
    cap_half = 2.0 * math.asin(math.sqrt(min(depth / (2.0 * radius), 1.0)))
    grid_from = min(CAP_GRID_ELEMENTS * d_theta, CAP_GRID_MAX_RAD)
    blend_from = (1.0 - CAP_BLEND) * grid_from
    on_grid = 1.0  # the grid's share of the result
    if cap_half < grid_from:
        on_grid = 0.0
        if cap_half > blend_from:
            x = (cap_half - blend_from) / (grid_from - blend_from)
            on_grid = x * x * (3.0 - 2.0 * x)
    if on_grid > 0.0:
        flat_grid(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
                  sin_sub_p, radius, d0, s1, s2, s3, v1, v2, v3, abs_omega, spin_sign, us, k,
                  cutting, acc)
    if on_grid < 1.0:
        for i in range(12):
            if i != 8:
                acc[i] *= on_grid
        for i in range(ACC_JACOBIAN, N_ACC):
            acc[i] *= on_grid
        exact = 1.0 - on_grid
        acc[11] += exact * 2.0 * math.pi * radius * depth  # the cap's area
        if cutting:
            measure = cut_cap(s1, s2, s3, v1, v2, v3, depth, radius, abs_omega, spin_sign, us,
                              k, exact, acc)
            if on_grid == 0.0 and measure > 0.0:
                # As many elements as the cut region covers (at least one).
                acc[8] = min(math.ceil(measure / (d_theta * d_phi)),
                             float(cos_t.shape[0] * cos_p.shape[0]))
    finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out)


@hot_kernel
def flat_grid(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
              sin_sub_p, radius, d0, s1, s2, s3, v1, v2, v3, abs_omega, spin_sign, us, k,
              cutting, acc):
    """The cut against a flat surface on the burr grid, added to the tool-frame ``acc``.

    ``d0``: depth of the surface below the burr centre, mm; (s1, s2, s3): outward surface
    normal and (v1, v2, v3): feed, mm/s, in the tool frame; the rest as :func:`cut_flat`.
    """
    w_force = us * radius * d_theta * d_phi / abs_omega if cutting else 0.0
    half_dt = 0.5 * d_theta * radius
    half_dp = 0.5 * d_phi * radius
    area_unit = radius * radius * d_theta * d_phi
    n_theta = cos_t.shape[0]
    m = cos_sub_t.shape[0]
    m2 = float(m * m)
    # A plane cuts from the sphere a cap of area 2πR·(d0 + R); no element can hold more bone
    # than that. Where the depth peaks inside an element (first touch) the linearized fraction
    # overestimates wildly, and this bound makes force and removal vanish continuously there.
    cap_area = 2.0 * math.pi * radius * (d0 + radius)
    # The depth is linearized across an element; its second-order remainder is bounded by
    # R/2·(dθ/2 + dφ/2)² (all second derivatives of s·n are ≤ 1). An element whose linear
    # range misses the surface by less than that may still be crossed, so it is refined.
    curve = 0.5 * radius * (0.5 * d_theta + 0.5 * d_phi) ** 2 if m > 1 else 0.0
    curve_sub = curve / m2
    # The same bound for n·v_f: where it may change sign across an element, the sub-centres
    # would face the feed differently from the centre the whole element is judged by.
    speed = math.sqrt(v1 * v1 + v2 * v2 + v3 * v3)
    curve_v = 0.5 * speed * (0.5 * d_theta + 0.5 * d_phi) ** 2
    # An element's removal integrated exactly: R²·dφ·(sinc·(v·e_ρ)·∫sin²θ dθ +
    # v3·∫sin θ cos θ dθ) over its band (add_removal_correction).
    sinc = math.sin(0.5 * d_phi) / (0.5 * d_phi)
    sin_dt = math.sin(d_theta)
    r2_dp = radius * radius * d_phi
    for kk in range(cos_p.shape[0]):
        cp = cos_p[kk]
        sp = sin_p[kk]
        su = s1 * cp + s2 * sp  # s·(cos φ e1 + sin φ e2)
        s_phi = -s1 * sp + s2 * cp  # s·φ̂
        vu = v1 * cp + v2 * sp
        for j in range(n_theta):
            ct = cos_t[j]
            st = sin_t[j]
            g0 = d0 - radius * (st * su + ct * s3)
            # Depth changes across the element: ∂g/∂θ = −R·s·θ̂, ∂g/∂φ = −R·sin θ·s·φ̂.
            half_a = half_dt * abs(ct * su - st * s3)
            half_b = half_dp * st * abs(s_phi)
            reach = half_a + half_b + curve
            if g0 <= -reach:
                continue
            w_area = area_unit * st
            vn = st * vu + ct * v3
            vary = (0.5 * d_theta * abs(ct * vu - st * v3)
                    + 0.5 * d_phi * st * abs(-v1 * sp + v2 * cp) + curve_v)
            exact_less_mid = 0.0
            if cutting and vn > -vary:
                # Where n·v_f keeps its sign across the element, its exact integral; where the
                # facing edge crosses it, the centre decides, and its part facing the feed is
                # the positive part of n·v_f linear across it (the midpoint counts all or none).
                share = facing_share(vn, vary)
                if share > 0.0:
                    band_ss = 0.5 * d_theta - 0.5 * (ct * ct - st * st) * sin_dt  # ∫ sin²θ dθ
                    band_sc = st * ct * sin_dt  # ∫ sin θ cos θ dθ
                    exact_less_mid = (r2_dp * (sinc * vu * band_ss + v3 * band_sc)
                                      - w_area * vn) * share
                exact_less_mid += w_area * (positive_mean(
                    vn, 0.5 * d_theta * abs(ct * vu - st * v3),
                    0.5 * d_phi * st * abs(-v1 * sp + v2 * cp)) - max(vn, 0.0))
            if m == 1 or g0 >= reach:
                frac = min(box_fraction(g0, half_a, half_b), cap_area / w_area)
                cut_element(acc, frac, st, ct, cp, sp, vu, v3, w_force, w_area, abs_omega, k,
                            spin_sign, radius, cutting)
                if exact_less_mid != 0.0 and frac > 0.0:
                    add_removal_correction(acc, frac * exact_less_mid, us, abs_omega, spin_sign)
                continue
            # The surface crosses this element and its trace is curved in (θ, φ): refine the
            # linear fraction and the centre-point integrand on m×m sub-elements.
            vn = st * vu + ct * v3
            # Sub-centres may face the feed where the centre does not, or not where it does:
            # then only the mean fraction, applied at the centre, grows steadily into the
            # centre-point value the element takes once it is wholly in bone.
            straddles = cutting and abs(vn) < vary
            count_before = acc[8]
            mean = 0.0
            for a in range(m):
                ct2, st2 = rotated(ct, st, cos_sub_t[a], sin_sub_t[a])
                for b in range(m):
                    cp2, sp2 = rotated(cp, sp, cos_sub_p[b], sin_sub_p[b])
                    frac = _sub_fraction(ct2, st2, cp2, sp2, s1, s2, s3, d0, radius,
                                         half_dt / m, half_dp / m, curve_sub, cap_area,
                                         area_unit / m2)
                    if frac <= 0.0:
                        continue
                    mean += frac
                    if not straddles:
                        cut_element(acc, frac, st2, ct2, cp2, sp2, v1 * cp2 + v2 * sp2, v3,
                                    w_force / m2, area_unit * st2 / m2, abs_omega, k,
                                    spin_sign, radius, cutting)
            mean /= m2
            if straddles:
                if mean > 0.0:
                    cut_element(acc, mean, st, ct, cp, sp, vu, v3, w_force, w_area, abs_omega,
                                k, spin_sign, radius, cutting)
                    if exact_less_mid != 0.0:
                        add_removal_correction(acc, mean * exact_less_mid, us, abs_omega,
                                               spin_sign)
            elif mean > WHOLE_FROM:
                # The m×m sub-centres integrate a whole element slightly differently from its
                # centre, which it is integrated at once wholly in bone: shift the sum toward
                # the centre value as the element fills, so nothing steps when the surface
                # leaves it (a step down would break force growing with depth). The shift is
                # ~0.1 % of the element's cut, so it cannot outweigh the filling itself.
                x = (mean - WHOLE_FROM) / (1.0 - WHOLE_FROM)
                shift = x * x
                for a in range(m):
                    ct2, st2 = rotated(ct, st, cos_sub_t[a], sin_sub_t[a])
                    for b in range(m):
                        cp2, sp2 = rotated(cp, sp, cos_sub_p[b], sin_sub_p[b])
                        cut_element(acc, -shift, st2, ct2, cp2, sp2, v1 * cp2 + v2 * sp2, v3,
                                    w_force / m2, area_unit * st2 / m2, abs_omega, k,
                                    spin_sign, radius, cutting)
                cut_element(acc, shift, st, ct, cp, sp, vu, v3, w_force, w_area, abs_omega, k,
                            spin_sign, radius, cutting)
                if exact_less_mid != 0.0:
                    add_removal_correction(acc, shift * exact_less_mid, us, abs_omega,
                                           spin_sign)
            if acc[8] > count_before:  # a refined element counts once
                acc[8] = count_before + 1.0


@hot_kernel
def _sub_fraction(ct2, st2, cp2, sp2, s1, s2, s3, d0, radius, half_dt, half_dp, curve,
                  cap_area, area_unit):
    """Bone fraction of one sub-element (centre (θ, φ) by cos and sin; extents half_dt,
    half_dp, mm; area_unit = R²·dθ·dφ of the sub-element, mm²)."""
    su2 = s1 * cp2 + s2 * sp2
    s_n = st2 * su2 + ct2 * s3
    g = d0 - radius * s_n
    ha = half_dt * abs(ct2 * su2 - st2 * s3)
    hb = half_dp * st2 * abs(-s1 * sp2 + s2 * cp2)
    if g <= -(ha + hb + curve):
        return 0.0
    # The depth's mean curvature term over the sub-element (g_θθ = R·s·n, g_φφ = R·sin θ·s·e_ρ
    # per rad²): the shift of the linearized depth that is exact on average over where the
    # surface's trace crosses it (kernels_revolved._sub_fraction).
    g += (s_n * half_dt * half_dt + st2 * su2 * half_dp * half_dp) / (6.0 * radius)
    return min(box_fraction(g, ha, hb), cap_area / (area_unit * st2))
