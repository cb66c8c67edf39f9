"""numba kernel of the cutting-force model for a burr of any shape (a surface of revolution).

Same conventions and result layout as kernels_flat.cut_flat (kernels.OUT_*, accumulated in the tool
frame and finished by kernels.finish); the elements are the (s, φ) elements of
revolved.RevolvedGrid, and each element's force carries a normal ratio and an edge ratio
(shapes.Cutter.force_ratios) instead of the abrasive K alone.
"""

from __future__ import annotations

import math

from ..hot_kernel import hot_kernel
from .kernels import add_jacobian, add_totals, box_fraction, finish, rotated
from .kernels_flat import add_removal_correction, facing_share, positive_mean, start_flat

# Rows of the grid's element and sub-element tables (revolved.RevolvedGrid.elem / .sub).
_RHO, _Z, _NR, _NZ, _TR, _TZ, _KAPPA = 0, 1, 2, 3, 4, 5, 6


@hot_kernel
def accumulate_element(acc, frac, rho, z, nr, nz, tr, tz, cp, sp, vn, w_force, w_area,
                       abs_omega, kn, kg, spin_sign):
    """Add one element's cut (it faces the feed: vn = n·v_f > 0, mm/s) to ``acc``.

    The force on the burr is −|Ft|·ĉ − kn·|Ft|·n + spin_sign·kg·|Ft|·t̂ with ĉ = v_t/|v_t| =
    spin_sign·φ̂, n the outward normal and t̂ the profile tangent (tip → top); the edge part
    changes side with the spin because the edges' inclination to ĉ does.

    Args:
        w_force: Us·ds·dφ/|ω|, N·s/mm (the cancelled weight times Us); w_area: ρ·ds·dφ, mm².
    """
    ft = w_force * vn * frac
    accumulate_forces_revolved(acc, ft, kn * ft, spin_sign * kg * ft, w_area * frac, vn, rho,
                               z, nr, nz, tr, tz, cp, sp, abs_omega * rho, spin_sign)


@hot_kernel
def accumulate_forces_revolved(acc, ft, fn, fg, area, vn, rho, z, nr, nz, tr, tz, cp, sp,
                               speed, spin_sign):
    """One element's cut into the tool-frame ``acc`` (shape (N_ACC,)): tangential |Ft| =
    ``ft``, normal ``fn`` along −n, edge ``fg`` along the profile tangent (N), at
    x = (ρ cos φ, ρ sin φ, z) (mm) with n = (n_ρ cos φ, n_ρ sin φ, n_z); ``area`` in bone,
    mm²; vn = n·v_f > 0, mm/s; ``speed`` = |v_t|, mm/s. Torque about the reference centre
    x × F; Jacobian as kernels.accumulate_forces."""
    n1 = nr * cp
    n2 = nr * sp
    f1 = ft * spin_sign * sp - fn * n1 + fg * tr * cp
    f2 = -ft * spin_sign * cp - fn * n2 + fg * tr * sp
    f3 = -fn * nz + fg * tz
    acc[0] += f1
    acc[1] += f2
    acc[2] += f3
    x1 = rho * cp
    x2 = rho * sp
    acc[3] += x2 * f3 - z * f2
    acc[4] += z * f1 - x1 * f3
    acc[5] += x1 * f2 - x2 * f1
    m1 = n1 / vn
    m2 = n2 / vn
    m3 = nz / vn
    add_jacobian(acc, f1, f2, f3, m1, m2, m3)
    add_totals(acc, ft, area, vn, speed)


@hot_kernel
def _element(acc, frac, rho, z, nr, nz, tr, tz, cp, sp, v1, v2, v3, w_force, w_area,
             abs_omega, kn, kg, spin_sign, cutting):
    acc[11] += w_area * frac
    if not cutting:
        return
    vn = nr * (v1 * cp + v2 * sp) + nz * v3
    if vn > 0.0:
        accumulate_element(acc, frac, rho, z, nr, nz, tr, tz, cp, sp, vn, w_force, w_area,
                           abs_omega, kn, kg, spin_sign)


@hot_kernel
def lowest_reach(segments, s_perp, s3):
    """min over the burr's surface of s·x (mm, x from the reference centre): the point that
    reaches deepest along −s. ``s_perp`` ≥ 0 and ``s3`` are the parts of s across and along
    the axis; ``segments`` (n_seg, 6) as revolved.RevolvedGrid.segments. Exact for lines
    (an endpoint) and arcs (an endpoint or the arc's own extreme)."""
    lowest = math.inf
    for i in range(segments.shape[0]):
        if segments[i, 0] == 0.0:  # line (ρ0, z0, ρ1, z1)
            lowest = min(lowest, -segments[i, 1] * s_perp + segments[i, 2] * s3,
                         -segments[i, 3] * s_perp + segments[i, 4] * s3)
            continue
        rc = segments[i, 1]
        zc = segments[i, 2]
        r = segments[i, 3]
        lo = min(segments[i, 4], segments[i, 5])
        hi = max(segments[i, 4], segments[i, 5])
        # On the arc s·x = −(ρc + r cos ψ)·s_perp + (zc + r sin ψ)·s3 = base − A·cos(ψ − γ),
        # A = r·|s|.
        base = -rc * s_perp + zc * s3
        amp = r * math.sqrt(s_perp * s_perp + s3 * s3)
        gamma = math.atan2(-s3, s_perp)
        for psi in (lo, hi):
            lowest = min(lowest, base - amp * math.cos(psi - gamma))
        for turn in (-2.0 * math.pi, 0.0, 2.0 * math.pi):
            if lo <= gamma + turn <= hi:
                lowest = min(lowest, base - amp)
    return lowest


@hot_kernel
def _sub_fraction(sub, j, ia, cp, sp, cos_off, sin_off, s1, s2, s3, d0, half_s, half_p,
                  curve):
    """Bone fraction of sub-element (ia, ·) of element j at the φ-offset (cos_off, sin_off)
    from the sector (cp, sp); half extents half_s (mm) and half_p (rad)."""
    cp2 = cp * cos_off - sp * sin_off
    sp2 = sp * cos_off + cp * sin_off
    su2 = s1 * cp2 + s2 * sp2
    rho2 = sub[_RHO, j, ia]
    g = d0 - rho2 * su2 - sub[_Z, j, ia] * s3
    ha = half_s * abs(sub[_TR, j, ia] * su2 + sub[_TZ, j, ia] * s3)
    hb = half_p * rho2 * abs(-s1 * sp2 + s2 * cp2)
    if g <= -(ha + hb + curve):
        return 0.0
    # The depth's curvature (g_ss = κ·s·n, g_φφ = ρ·s·e_ρ) moves the surface's trace off the
    # linearized one; its mean over the sub-element, (g_ss·half_s² + g_φφ·half_p²)/6, is the
    # shift that is exact on average over where the trace crosses. Without it the fraction
    # leans one way wherever the cut is a convex cap: +0.19 % removal (the sphere, 90°).
    s_n = sub[_NR, j, ia] * su2 + sub[_NZ, j, ia] * s3
    g += (sub[_KAPPA, j, ia] * s_n * half_s * half_s + rho2 * su2 * half_p * half_p) / 6.0
    return box_fraction(g, ha, hb)


@hot_kernel
def cut_flat_revolved(elem, ds, sub, ds_sub, cos_p, sin_p, d_phi, cos_sub_p, sin_sub_p,
                      segments, moments, centre, axis, v_feed, omega, us, kn, kg, cutting,
                      plane_point, plane_normal, acc, out):
    """Cutting force of a burr of revolution against a flat bone half-space. One call per
    evaluation; no allocation.

    Args:
        elem: (7, n_s) element rows ρ, z, n_ρ, n_z, t_ρ, t_z, κ (revolved.RevolvedGrid).
        ds: (n_s,) element lengths along the profile, mm.
        sub: (7, n_s, m) the same rows at the m sub-element midpoints along s of each element.
        ds_sub: (n_s,) sub-element lengths, mm.
        cos_p, sin_p: (n_phi,) sector midpoints; d_phi: rad.
        cos_sub_p, sin_sub_p: (m,) φ-offsets of the sub-element centres (m = 1: no split).
        segments: (n_seg, 6) the exact profile (revolved.RevolvedGrid.segments).
        moments: (2, n_s) ∫ρ·n_ρ ds and ∫ρ·n_z ds per element, mm² (RevolvedGrid.moments):
            an element counted whole removes exactly dφ·(sinc·(v·e_ρ)·∫ρn_ρ + v_z·∫ρn_z)
            (``add_removal_correction``).
        centre: (3,) the burr's reference centre, mm.  axis: (3,) toward the handle.
        v_feed: (3,) velocity of the burr relative to the bone, mm/s.
        omega: signed spindle speed along the axis, rad/s (forward is negative).
        us: Us, N/mm².  kn, kg: normal and edge force ratios (shapes.Cutter.force_ratios).
        cutting: False below the minimum cutting speed (contact area only).
        plane_point, plane_normal: (3,) the bone surface and its unit outward normal.
        acc: (N_ACC,) scratch; out: (N_OUT,) result, laid out as kernels.OUT_*.
    """
    # An element centre x lies g = d0 − s·x deep in bone (positive inside).
    (d0, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, s1, s2, s3, v1, v2,
     v3) = start_flat(centre, axis, v_feed, plane_point, plane_normal, acc, out)
    # Exactly out of bone: no element may report a sliver its linearized depth invents.
    if d0 <= lowest_reach(segments, math.sqrt(s1 * s1 + s2 * s2), s3):
        return
    abs_omega = abs(omega)
    spin_sign = 1.0 if omega >= 0.0 else -1.0
    w_unit = us * d_phi / abs_omega if cutting else 0.0
    half_dp = 0.5 * d_phi
    # ∫ cos φ over a sector is its midpoint value times sin(dφ/2)/(dφ/2).
    sinc = math.sin(half_dp) / half_dp
    speed = math.sqrt(v1 * v1 + v2 * v2 + v3 * v3)
    n_s = ds.shape[0]
    m = cos_sub_p.shape[0]
    mf = float(m)
    for kk in range(cos_p.shape[0]):
        cp = cos_p[kk]
        sp = sin_p[kk]
        su = s1 * cp + s2 * sp  # s·e_ρ(φ)
        s_phi = abs(-s1 * sp + s2 * cp)  # |s·φ̂|
        vu = v1 * cp + v2 * sp
        v_phi = abs(-v1 * sp + v2 * cp)
        for j in range(n_s):
            rho = elem[_RHO, j]
            z = elem[_Z, j]
            tr = elem[_TR, j]
            tz = elem[_TZ, j]
            kappa = elem[_KAPPA, j]
            g0 = d0 - rho * su - z * s3
            # ∂g/∂s = −(t_ρ·s·e_ρ + t_z·s3), ∂g/∂φ = −ρ·s·φ̂.
            a = 0.5 * ds[j]
            half_a = a * abs(tr * su + tz * s3)
            half_b = half_dp * rho * s_phi
            # Second-order remainder of the linearized depth: |g_ss| ≤ κ, |g_sφ| ≤ 1,
            # |g_φφ| ≤ ρ, so a crossing the linear range misses is still refined.
            curve = (0.5 * (kappa * a * a + 2.0 * a * half_dp + (rho + a) * half_dp * half_dp)
                     if m > 1 else 0.0)
            reach = half_a + half_b + curve
            if g0 <= -reach:
                continue
            nr = elem[_NR, j]
            nz = elem[_NZ, j]
            w_area = rho * ds[j] * d_phi
            # n·v_f may change sign inside the element (|n'| = κ along s, second derivatives
            # ≤ |v|·(κ·a + dφ/2)²): then the facing test is made at the sub-centres whether or
            # not the surface crosses it, or its cut would step when the surface leaves it.
            vn = nr * vu + nz * v3
            vn_a = a * kappa * abs(tr * vu + tz * v3)
            vn_b = half_dp * abs(nr) * v_phi
            vary = vn_a + vn_b + 0.5 * speed * (kappa * a + half_dp) ** 2
            straddles = m > 1 and cutting and abs(vn) < vary
            # The element's removal integrated exactly in s and φ, less its midpoint value;
            # where the facing edge crosses an element its centre decides (unrefined), and its
            # part facing the feed is the positive part of n·v_f linear across it
            # (kernels_flat.flat_grid).
            exact_less_mid = 0.0
            if cutting and vn > -vary:
                share = facing_share(vn, vary)
                if share > 0.0:
                    exact_less_mid = (d_phi * (sinc * vu * moments[0, j] + v3 * moments[1, j])
                                      - w_area * vn) * share
                if not straddles:
                    exact_less_mid += w_area * (positive_mean(vn, vn_a, vn_b) - max(vn, 0.0))
            if not straddles and (m == 1 or g0 >= reach):
                frac = box_fraction(g0, half_a, half_b)
                _element(acc, frac, rho, z, nr, nz, tr, tz, cp, sp, v1, v2, v3,
                         w_unit * ds[j], w_area, abs_omega, kn, kg, spin_sign, cutting)
                if exact_less_mid != 0.0 and frac > 0.0:
                    add_removal_correction(acc, frac * exact_less_mid, us, abs_omega,
                                           spin_sign)
                continue
            # m×m sub-elements, exact on the profile. Each counts with its fraction less the
            # element's mean fraction and the centre with the mean: an element wholly in bone
            # then gives exactly its unrefined value, so nothing steps when the surface leaves
            # it (the sphere kernel's rule, kernels_flat.flat_grid).
            a2 = 0.5 * ds_sub[j]
            hp2 = half_dp / mf
            curve_sub = curve / (mf * mf)
            mean = 0.0
            for ia in range(m):
                for ib in range(m):
                    mean += _sub_fraction(sub, j, ia, cp, sp, cos_sub_p[ib], sin_sub_p[ib],
                                          s1, s2, s3, d0, a2, hp2, curve_sub)
            if mean <= 0.0:
                continue
            mean = 0.0 if straddles else mean / (mf * mf)
            count_before = acc[8]
            w_force = w_unit * ds_sub[j] / mf
            for ia in range(m):
                rho2 = sub[_RHO, j, ia]
                w_area2 = rho2 * ds_sub[j] * d_phi / mf
                for ib in range(m):
                    frac = _sub_fraction(sub, j, ia, cp, sp, cos_sub_p[ib], sin_sub_p[ib],
                                         s1, s2, s3, d0, a2, hp2, curve_sub)
                    if frac == mean:
                        continue
                    cp2, sp2 = rotated(cp, sp, cos_sub_p[ib], sin_sub_p[ib])
                    _element(acc, frac - mean, rho2, sub[_Z, j, ia], sub[_NR, j, ia],
                             sub[_NZ, j, ia], sub[_TR, j, ia], sub[_TZ, j, ia], cp2, sp2,
                             v1, v2, v3, w_force, w_area2, abs_omega, kn, kg, spin_sign,
                             cutting)
            if mean > 0.0:
                _element(acc, mean, rho, z, nr, nz, tr, tz, cp, sp, v1, v2, v3,
                         w_unit * ds[j], w_area, abs_omega, kn, kg, spin_sign, cutting)
                if exact_less_mid != 0.0:
                    add_removal_correction(acc, mean * exact_less_mid, us, abs_omega,
                                           spin_sign)
            if acc[8] > count_before:  # a refined element counts once
                acc[8] = count_before + 1.0
    finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out)
