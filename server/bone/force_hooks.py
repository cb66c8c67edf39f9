"""What the force stage asks of a burr's shape, answered per shape at compile time.

``force.cut_voxels`` is one kernel for every burr: its passes (which corners an element
needs, their samples in two levels, the elements' integration on their corners or on
sub-elements, the outward normal) are the same for all. Where the shapes differ — their
elements' geometry, the force each element carries, the smoothing between the two
integration rules, the normal's fallback — it calls the hooks below, whose bodies numba
picks by the type of the burr's tables (``tick_tables.SphereTick``, ``RevolvedTick``) and
inlines (``hot_kernel.hot_hook``).

Each body keeps the arithmetic its shape's own kernel had, operation for operation: a
groove's every output is what it was to the last bit (sums in the same order, the same
products fused).
"""

from __future__ import annotations

import math

from ..hot_kernel import hot_hook, hot_inline, hot_kernel
from ..model.kernels import (
    OUT_COMPONENTS,
    OUT_SURFACE_NORMAL,
    accumulate_forces,
    rotated,
    tool_basis,
)
from ..model.kernels_revolved import accumulate_forces_revolved
from .cutters import RevolvedReach, SphereReach, is_shape, no_shape
from .sampling import sample_bone
from .tick_tables import RevolvedTick, SphereTick
from .voxels import sphere_reach, stencils_inside

#: Corner markers between the two sampling levels (real fractions are in [0, 1]).
PENDING = -1.0
UNNEEDED = -2.0

#: The sphere's elements whose corner fractions differ by less than BLEND_SPREAD_LO are
#: integrated from their corners, by more than BLEND_SPREAD_HI on m×m sub-elements, and between
#: the two both ways, blended smoothly. A crossing bone surface makes the corners differ by
#: ~1; smooth partial availability (the sides of the groove the burr is ploughing) by a few
#: per cent, where the corner mean is exact enough. A single switch stepped the force by the
#: two rules' difference whenever a corner crossed it (plunges: force against depth fell by up
#: to 3 % and removal by 12 % in steps).
BLEND_SPREAD_LO = 0.2
BLEND_SPREAD_HI = 0.3
#: The other burrs switch at this spread: an end disc or a rim meets the bone's surface at a
#: shallow angle across many elements whose corner mean is then biased (flat cylinder,
#: perpendicular 30°, fresh block: +2.2 % at 0.25, +1.2 % at 0.05).
SMOOTH_SPREAD_REVOLVED = 0.05
#: The sphere's outward normal is −(G·|G| + FALLBACK·N), G = Σ w·∇ρ over the patches the
#: original surface crosses (mm), N = Σ area·n over the patches in bone (mm²): the density
#: gradient wherever the surface crosses the cutting zone, fading continuously into the
#: in-bone normals' mean as it leaves it, instead of switching to it only when no patch is
#: crossed (a few patches left near the zone's edge gave a noisy gradient: the normal force
#: jumped by 45 % in plunges on an oblique grid). Against a groove's G of a few mm the
#: fallback's part is ~1e-7.
FALLBACK = 5e-6

#: While the elements are integrated, ``acc`` holds the outward normal's sums where the normal
#: and the force's components go at the end (``model.kernels.OUT_SURFACE_NORMAL``,
#: ``OUT_COMPONENTS``): Σ area·n over the patches in bone (tool frame, mm²) and Σ w·∇ρ over
#: those the bone's surface crosses (grid frame, mm). Summed in memory rather than in locals:
#: the products then fuse into their sums as they did in each shape's own kernel.
ACC_NORMALS = OUT_SURFACE_NORMAL
ACC_GRADIENT = OUT_COMPONENTS

# Rows of a revolved grid's element and sub-element tables (revolved.RevolvedGrid.elem, .sub).
_RHO, _Z, _NR, _NZ, _TR, _TZ = 0, 1, 2, 3, 4, 5

#: A patch's half-sides for ``sampling.sample_bone``: unused by a burr without a path.
_NO_PATCH = (0.0, 0.0, 0.0)


@hot_inline
def patch_half_sides(radius, d_theta, d_phi, m):
    """Half-sides of a sub-element (m×m per element of dθ × dφ on a sphere of ``radius`` mm)
    along θ and, per sin θ, along φ, mm: the patch a sample's path share is taken over
    (``history.history_share``); a patch at θ reaches at most their sum."""
    return 0.5 * radius * d_theta / m, 0.5 * radius * d_phi / m



@hot_kernel
def sample_bone_revolved(density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx,
                         hy, hz, cx, cy, cz, profile, geo, cache, o0, o1, o2, tick):
    """``sampling.sample_bone`` for a burr of revolution (it keeps no path), called rather
    than inlined (inlined at its two call sites it compiled twice over, for little: see
    tick-levers.md): (fraction, us_fraction, usk_fraction, gx, gy, gz) at p (grid frame,
    mm); ``profile``, ``geo`` as ``cutters.RevolvedReach``."""
    return sample_bone(RevolvedReach(profile, geo), density, swept, labels, us_tab, usk_tab,
                       brick_bone, px, py, pz, hx, hy, hz, cx, cy, cz, cache, o0, o1, o2, tick,
                       _NO_PATCH, _NO_PATCH, False)


@hot_inline
def normal_sums(acc):
    """(Σ w·∇ρ: 3 floats, Σ area·n: 3 floats) from ``acc`` (``ACC_GRADIENT``, ``ACC_NORMALS``),
    which are cleared for the normal and the components."""
    sums = (acc[ACC_GRADIENT], acc[ACC_GRADIENT + 1], acc[ACC_GRADIENT + 2], acc[ACC_NORMALS],
            acc[ACC_NORMALS + 1], acc[ACC_NORMALS + 2])
    for n in range(3):
        acc[ACC_GRADIENT + n] = 0.0
        acc[ACC_NORMALS + n] = 0.0
    return sums


def force_frame(burr, axis):
    """The tool frame (e1, e2, e3) as 9 floats, grid frame, for the unit tool ``axis`` (3,)."""


@hot_hook(force_frame)
def _force_frame(burr, axis):
    if is_shape(burr, SphereTick):
        return lambda burr, axis: tool_basis(axis[0], axis[1], axis[2])
    if is_shape(burr, RevolvedTick):
        def revolved(burr, axis):
            geo = burr.geo  # filled by the carve stage (carve_revolved.fill_geometry)
            return geo[0], geo[1], geo[2], geo[3], geo[4], geo[5], geo[6], geo[7], geo[8]
        return revolved
    return no_shape(burr)


def force_setup(burr, omega, cutting, has_cut, feed_speed, bone, spot):
    """The tick's constants of the force stage: (reach, interior, rows, consts).

    reach: the burr as the samplers see it (``cutters``).  interior: every sample's stencil
    lies inside the grid (``voxels.stencils_inside``).  rows: the element rows' normal across
    and along the axis, two (n_rows,) arrays.  consts: the shape's own constants for the
    hooks below. ``bone``: the voxel arrays (density, swept, labels, us_tab, usk_tab,
    brick_bone); ``spot``: (hx, hy, hz, cx, cy, cz), the spacing and the burr's centre, mm.
    """


@hot_hook(force_setup)
def _force_setup(burr, omega, cutting, has_cut, feed_speed, bone, spot):
    if is_shape(burr, SphereTick):
        def sphere(burr, omega, cutting, has_cut, feed_speed, bone, spot):
            hx, hy, hz, cx, cy, cz = spot
            density = bone[0]
            radius = burr.radius
            d_theta = burr.d_theta
            d_phi = burr.d_phi
            w_unit = radius * d_theta * d_phi / abs(omega) if cutting else 0.0
            area_unit = radius * radius * d_theta * d_phi
            r_in2, r_out2 = sphere_reach(radius, hx, hy, hz)
            m = burr.cos_sub_t.shape[0]
            inv_m2 = 1.0 / float(m * m)  # the sub-element loop multiplies: divisions queue
            inv_feed = 1.0 / feed_speed if has_cut else 0.0
            half_t, half_p = patch_half_sides(radius, d_theta, d_phi, m)
            interior = stencils_inside(density.shape[0], density.shape[1], density.shape[2],
                                       hx, hy, hz, cx, cy, cz, radius)
            reach = SphereReach(radius, r_in2, r_out2, burr.path_cand)
            return (reach, interior, (burr.sin_t, burr.cos_t),
                    (w_unit, area_unit, inv_m2, inv_feed, half_t, half_p, has_cut))
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, omega, cutting, has_cut, feed_speed, bone, spot):
            w_unit = burr.d_phi / abs(omega) if cutting else 0.0
            elem = burr.elem
            return (RevolvedReach(burr.profile, burr.geo), False, (elem[_NR], elem[_NZ]),
                    (w_unit, float(burr.cos_sub_p.shape[0])))
        return revolved
    return no_shape(burr)


@hot_inline
def sphere_sample(reach, consts, st, ct, cp, sp, bone, spot, basis, cached, interior):
    """``sampling.sample_bone`` at the point of the sphere at polar (sin θ, cos θ) = (st, ct)
    and azimuth (cp, sp) about the tool axis, with its patch (``patch_half_sides``, in
    ``consts``) for the path's share: (fraction, us_fraction, usk_fraction, gx, gy, gz)."""
    density, swept, labels, us_tab, usk_tab, brick_bone = bone
    hx, hy, hz, cx, cy, cz = spot
    cache, o0, o1, o2, tick = cached
    half_t = consts[4]
    half_p = consts[5]
    radius = reach.radius
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    n1 = st * cp
    n2 = st * sp
    px = cx + radius * (n1 * e1x + n2 * e2x + ct * e3x)
    py = cy + radius * (n1 * e1y + n2 * e2y + ct * e3y)
    pz = cz + radius * (n1 * e1z + n2 * e2z + ct * e3z)
    h2 = half_p * st
    return sample_bone(
        reach, density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx, hy, hz, cx,
        cy, cz, cache, o0, o1, o2, tick,
        (half_t * (ct * cp * e1x + ct * sp * e2x - st * e3x),
         half_t * (ct * cp * e1y + ct * sp * e2y - st * e3y),
         half_t * (ct * cp * e1z + ct * sp * e2z - st * e3z)),
        (h2 * (cp * e2x - sp * e1x), h2 * (cp * e2y - sp * e1y), h2 * (cp * e2z - sp * e1z)),
        interior)


@hot_inline
def revolved_sample(reach, rho, z, cp, sp, bone, spot, basis, cached):
    """``sample_bone_revolved`` at the point (ρ, z) of the burr's profile (mm) at azimuth
    (cp, sp) about the tool axis: (fraction, us_fraction, usk_fraction, gx, gy, gz)."""
    density, swept, labels, us_tab, usk_tab, brick_bone = bone
    hx, hy, hz, cx, cy, cz = spot
    cache, o0, o1, o2, tick = cached
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    r1 = rho * cp
    r2 = rho * sp
    px = cx + r1 * e1x + r2 * e2x + z * e3x
    py = cy + r1 * e1y + r2 * e2y + z * e3y
    pz = cz + r1 * e1z + r2 * e2z + z * e3z
    return sample_bone_revolved(density, swept, labels, us_tab, usk_tab, brick_bone, px, py,
                                pz, hx, hy, hz, cx, cy, cz, reach.profile, reach.geo, cache, o0,
                                o1, o2, tick)


def ring_on_axis(burr, vert, j, n_rows, n_phi):
    """(on_axis, needed) for corner ring j: whether the ring is one point on the axis (sampled
    once for all its corners) and, if so, whether an element needs it. The sphere's poles
    are rings 0 and n_rows and count as needed by their corner k = 0's mark; another burr's
    rings on the axis are those at ρ = 0, needed if any of their corners is."""


@hot_hook(ring_on_axis)
def _ring_on_axis(burr, vert, j, n_rows, n_phi):
    if is_shape(burr, SphereTick):
        def sphere(burr, vert, j, n_rows, n_phi):
            return (j == 0 or j == n_rows), vert[j, 0, 0] == PENDING
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, vert, j, n_rows, n_phi):
            if burr.corners[0, j] != 0.0:
                return False, False
            for k in range(n_phi):
                if vert[j, k, 0] == PENDING:
                    return True, True
            return True, False
        return revolved
    return no_shape(burr)


def sample_corner(burr, consts, reach, vert, j, k, bone, spot, basis, cached, interior):
    """Sample the bone at corner (j, k) of the burr's element grid into ``vert[j, k]``
    (fraction, Us and Us·K fractions: ``sampling.sample_bone``). ``cached``: the tick's
    coverage cache and its origin, (cache, o0, o1, o2, tick)."""


@hot_hook(sample_corner)
def _sample_corner(burr, consts, reach, vert, j, k, bone, spot, basis, cached, interior):
    if is_shape(burr, SphereTick):
        def sphere(burr, consts, reach, vert, j, k, bone, spot, basis, cached, interior):
            frac, us_f, usk_f, _, _, _ = sphere_sample(
                reach, consts, burr.sin_tv[j], burr.cos_tv[j], burr.cos_pv[k], burr.sin_pv[k],
                bone, spot, basis, cached, interior)
            vert[j, k, 0] = frac
            vert[j, k, 1] = us_f
            vert[j, k, 2] = usk_f
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, consts, reach, vert, j, k, bone, spot, basis, cached, interior):
            frac, us_f, usk_f, _, _, _ = revolved_sample(
                reach, burr.corners[0, j], burr.corners[1, j], burr.cos_pv[k], burr.sin_pv[k],
                bone, spot, basis, cached)
            vert[j, k, 0] = frac
            vert[j, k, 1] = us_f
            vert[j, k, 2] = usk_f
        return revolved
    return no_shape(burr)


def refined_share(burr, spread):
    """The share of an element integrated on sub-elements, from the spread of its corners'
    fractions: 0 (its corner mean) to 1 (sub-elements only)."""


@hot_hook(refined_share)
def _refined_share(burr, spread):
    if is_shape(burr, SphereTick):
        def sphere(burr, spread):
            if spread >= BLEND_SPREAD_HI:
                return 1.0
            if spread > BLEND_SPREAD_LO:
                x = (spread - BLEND_SPREAD_LO) / (BLEND_SPREAD_HI - BLEND_SPREAD_LO)
                return x * x * (3.0 - 2.0 * x)
            return 0.0
        return sphere
    if is_shape(burr, RevolvedTick):
        return lambda burr, spread: 0.0 if spread <= SMOOTH_SPREAD_REVOLVED else 1.0
    return no_shape(burr)


def element_area(burr, consts, j, nr):
    """The area of an element of row j (normal across the axis ``nr``), mm²."""


@hot_hook(element_area)
def _element_area(burr, consts, j, nr):
    if is_shape(burr, SphereTick):
        return lambda burr, consts, j, nr: consts[1] * nr
    if is_shape(burr, RevolvedTick):
        return lambda burr, consts, j, nr: burr.elem[_RHO, j] * burr.ds[j] * burr.d_phi
    return no_shape(burr)


def element_force(burr, consts, acc, vert, j, k, k1, share, area, vn, nr, nz, cp, sp, motion):
    """Add the cut of element (j, k) integrated on its corners (Us and Us·K their mean) to
    ``acc``: ``share`` of it (1 − the refined share), ``area`` in bone (mm², already times the
    share), vn = n·v_f > 0 (mm/s), normal (nr, nz) across and along the axis, sector midpoint
    (cp, sp); ``motion``: (v1, v2, v3, cutting, abs_omega, spin_sign)."""


@hot_hook(element_force)
def _element_force(burr, consts, acc, vert, j, k, k1, share, area, vn, nr, nz, cp, sp, motion):
    if is_shape(burr, SphereTick):
        def sphere(burr, consts, acc, vert, j, k, k1, share, area, vn, nr, nz, cp, sp, motion):
            abs_omega = motion[4]
            spin_sign = motion[5]
            radius = burr.radius
            us_f = 0.25 * (vert[j, k, 1] + vert[j + 1, k, 1] + vert[j, k1, 1]
                           + vert[j + 1, k1, 1])
            usk_f = 0.25 * (vert[j, k, 2] + vert[j + 1, k, 2] + vert[j, k1, 2]
                            + vert[j + 1, k1, 2])
            scale = consts[0] * vn * share
            accumulate_forces(acc, scale * us_f, scale * usk_f, area, vn, nr, nz, cp, sp,
                              abs_omega * radius * nr, spin_sign, radius)
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, consts, acc, vert, j, k, k1, share, area, vn, nr, nz, cp, sp,
                     motion):
            abs_omega = motion[4]
            spin_sign = motion[5]
            elem = burr.elem
            rho = elem[_RHO, j]
            us_f = 0.25 * (vert[j, k, 1] + vert[j + 1, k, 1] + vert[j, k1, 1]
                           + vert[j + 1, k1, 1])
            scale = consts[0] * burr.ds[j] * vn
            ft = scale * us_f
            if burr.material_k:
                fn = scale * 0.25 * (vert[j, k, 2] + vert[j + 1, k, 2] + vert[j, k1, 2]
                                     + vert[j + 1, k1, 2])
            else:
                fn = burr.kn * ft
            accumulate_forces_revolved(acc, ft, fn, spin_sign * burr.kg * ft, area, vn, rho,
                                       elem[_Z, j], nr, nz, elem[_TR, j], elem[_TZ, j], cp, sp,
                                       abs_omega * rho, spin_sign)
        return revolved
    return no_shape(burr)


def sub_row(burr, consts, j, a, nr, nz, refined):
    """Sub-row a of element row j (normal (nr, nz)) as the shape's ``sub_element`` reads it."""


@hot_hook(sub_row)
def _sub_row(burr, consts, j, a, nr, nz, refined):
    if is_shape(burr, SphereTick):
        def sphere(burr, consts, j, a, nr, nz, refined):
            # θ of the sub-row: the row's (cos θ, sin θ) turned by the sub-step.
            ct2, st2 = rotated(nz, nr, burr.cos_sub_t[a], burr.sin_sub_t[a])
            return st2, ct2
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, consts, j, a, nr, nz, refined):
            sub = burr.sub
            rho2 = sub[_RHO, j, a]
            return (rho2, sub[_Z, j, a], sub[_NR, j, a], sub[_NZ, j, a],
                    rho2 * burr.ds_sub[j] * burr.d_phi / consts[1], sub[_TR, j, a],
                    sub[_TZ, j, a])
        return revolved
    return no_shape(burr)


def sub_element(burr, consts, reach, acc, j, row, cp2, sp2, refined, bone, spot, basis, cached,
                motion, interior):
    """Sample the sub-element at sub-row ``row`` (``sub_row``) and sector direction (cp2, sp2),
    add its area in bone (``acc[11]``), its cut, and its part of the outward normal's sums
    (``ACC_NORMALS``, ``ACC_GRADIENT``) to ``acc``."""


@hot_hook(sub_element)
def _sub_element(burr, consts, reach, acc, j, row, cp2, sp2, refined, bone, spot, basis,
                 cached, motion, interior):
    if is_shape(burr, SphereTick):
        def sphere(burr, consts, reach, acc, j, row, cp2, sp2, refined, bone, spot, basis,
                   cached, motion, interior):
            v1, v2, v3, cutting, abs_omega, spin_sign = motion
            w_unit, area_unit, inv_m2, inv_feed, _, _, has_cut = consts
            radius = reach.radius
            st2, ct2 = row
            n1 = st2 * cp2
            n2 = st2 * sp2
            frac, us_f, usk_f, gx, gy, gz = sphere_sample(reach, consts, st2, ct2, cp2, sp2, bone,
                                                          spot, basis, cached, interior)
            if frac <= 0.0:
                return
            w_area = area_unit * st2 * inv_m2 * refined
            area = w_area * frac
            acc[11] += area
            vn2 = n1 * v1 + n2 * v2 + ct2 * v3
            # Weighted by how fast the patch cuts: a crossing that slides out of the cutting
            # zone (where n·v_f → 0) fades out of the estimate instead of leaving it as a few
            # noisy gradients.
            w_grad = w_area * (max(vn2, 0.0) * inv_feed if has_cut else 1.0)
            if cutting and vn2 > 0.0:
                scale = w_unit * vn2 * inv_m2 * refined
                accumulate_forces(acc, scale * us_f, scale * usk_f, area, vn2, st2, ct2, cp2,
                                  sp2, abs_omega * radius * st2, spin_sign, radius)
            acc[ACC_GRADIENT] += w_grad * gx
            acc[ACC_GRADIENT + 1] += w_grad * gy
            acc[ACC_GRADIENT + 2] += w_grad * gz
            acc[ACC_NORMALS] += area * n1
            acc[ACC_NORMALS + 1] += area * n2
            acc[ACC_NORMALS + 2] += area * ct2
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, consts, reach, acc, j, row, cp2, sp2, refined, bone, spot, basis,
                     cached, motion, interior):
            v1, v2, v3, cutting, abs_omega, spin_sign = motion
            rho2, z2, nr2, nz2, w_area, tr2, tz2 = row
            frac, us_f, usk_f, gx, gy, gz = revolved_sample(reach, rho2, z2, cp2, sp2, bone, spot,
                                                            basis, cached)
            if frac <= 0.0:
                return
            area = w_area * frac
            acc[11] += area
            vn2 = nr2 * (v1 * cp2 + v2 * sp2) + nz2 * v3
            if cutting and vn2 > 0.0:
                scale = consts[0] * burr.ds_sub[j] / consts[1] * vn2
                ft = scale * us_f
                fn = scale * usk_f if burr.material_k else burr.kn * ft
                accumulate_forces_revolved(acc, ft, fn, spin_sign * burr.kg * ft, area, vn2,
                                           rho2, z2, nr2, nz2, tr2, tz2, cp2, sp2,
                                           abs_omega * rho2, spin_sign)
            acc[ACC_GRADIENT] += w_area * gx
            acc[ACC_GRADIENT + 1] += w_area * gy
            acc[ACC_GRADIENT + 2] += w_area * gz
            acc[ACC_NORMALS] += area * nr2 * cp2
            acc[ACC_NORMALS + 1] += area * nr2 * sp2
            acc[ACC_NORMALS + 2] += area * nz2
        return revolved
    return no_shape(burr)


def normal_direction(burr, acc, basis):
    """The direction the bone's outward surface normal points against (grid frame, any
    length; zero if there is none), from the summed density gradient and the in-bone
    area-weighted normals (``normal_sums``): the sphere blends the two (``FALLBACK``), the
    other burrs take the gradient where there is one."""


@hot_hook(normal_direction)
def _normal_direction(burr, acc, basis):
    if is_shape(burr, SphereTick):
        def sphere(burr, acc, basis):
            gsx, gsy, gsz, nsum1, nsum2, nsum3 = normal_sums(acc)
            wx, wy, wz = in_grid_frame(nsum1, nsum2, nsum3, basis)
            g_norm = math.sqrt(gsx * gsx + gsy * gsy + gsz * gsz)
            return (g_norm * gsx + FALLBACK * wx, g_norm * gsy + FALLBACK * wy,
                    g_norm * gsz + FALLBACK * wz)
        return sphere
    if is_shape(burr, RevolvedTick):
        def revolved(burr, acc, basis):
            gsx, gsy, gsz, nsum1, nsum2, nsum3 = normal_sums(acc)
            if gsx * gsx + gsy * gsy + gsz * gsz > 0.0:
                return gsx, gsy, gsz
            return in_grid_frame(nsum1, nsum2, nsum3, basis)
        return revolved
    return no_shape(burr)


@hot_inline
def in_grid_frame(n1, n2, n3, basis):
    """The tool-frame vector (n1, n2, n3) in the grid frame (``basis``: e1, e2, e3, 9 floats)."""
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    return (n1 * e1x + n2 * e2x + n3 * e3x, n1 * e1y + n2 * e2y + n3 * e3y,
            n1 * e1z + n2 * e2z + n3 * e3z)
