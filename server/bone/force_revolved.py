"""The cutting force of a burr of any shape (a surface of revolution) against a voxel bone.

The elements of ``revolved.RevolvedGrid`` with the cancelled weight ds·dφ/ω, each element's
share of bone from the voxels as ``force.cut_voxels`` takes it for the sphere: the original
density, trilinear, times the share of the surroundings no other burr position has swept
(what this burr covers counts as available, by its own coverage: ``carve_revolved``), sampled
at the element corners and on m×m sub-elements where the bone's surface crosses an element.
Each element's force carries the cutter's ratios (``kernels_revolved.accumulate_forces_revolved``),
or the materials' own K for an abrasive burr. The burr's path (``history``) is not consulted:
its capsules describe a sphere's sweep. :class:`RevolvedTables` holds what such a burr's tick
needs beside the engine's buffers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import N_ACC, N_OUT, finish, in_tool_frame
from ..model.kernels_revolved import accumulate_forces_revolved
from ..model.revolved import RevolvedGrid
from ..model.shapes import Abrasive, Burr
from .carve_revolved import N_GEO, profile_table, shape_bounds
from .cutters import RevolvedReach
from .force import PENDING, mark_needed, settle_fine
from .sampling import sample_bone
from .voxels import cache_origin, spacing_and_point

#: Elements whose corner fractions differ by more than this are integrated on sub-elements.
#: Tighter than the sphere's 0.25 (``force.SMOOTH_SPREAD``): an end disc or a rim meets the
#: bone's surface at a shallow angle across many elements whose corner mean is then biased
#: (flat cylinder, perpendicular 30°, fresh block: +2.2 % at 0.25, +1.2 % at 0.05).
SMOOTH_SPREAD = 0.05

# Rows of the grid's element and sub-element tables (revolved.RevolvedGrid.elem / .sub).
_RHO, _Z, _NR, _NZ, _TR, _TZ = 0, 1, 2, 3, 4, 5


def revolved_corners(burr: Burr, grid: RevolvedGrid) -> tuple[np.ndarray, np.ndarray,
                                                              np.ndarray]:
    """The element corners of ``grid``: (ρ, z) at the n_s + 1 element boundaries along the
    profile, float64 (2, n_s + 1), mm, exact on the profile; cos and sin of the n_phi sector
    edges (k·dφ), float64 (n_phi,) each."""
    profile = burr.shape.profile()
    edges = np.concatenate(([0.0], np.cumsum(grid.ds)))
    starts = np.concatenate(([0.0], np.cumsum([seg.length_mm for seg in profile])))
    corners = np.empty((2, grid.n_s + 1))
    for n, s in enumerate(edges):
        i = min(int(np.searchsorted(starts, s, side="right")) - 1, len(profile) - 1)
        seg = profile[i]
        u = min(max((s - starts[i]) / seg.length_mm, 0.0), 1.0)
        rho, z = seg.at(np.array([u]))[:2]
        corners[0, n] = max(float(rho[0]), 0.0)
        corners[1, n] = float(z[0])
    for end in (0, grid.n_s):
        corners[0, end] = 0.0  # the tip and the top lie on the axis
    phi = np.arange(grid.n_phi) * grid.d_phi
    return (np.ascontiguousarray(corners), np.ascontiguousarray(np.cos(phi)),
            np.ascontiguousarray(np.sin(phi)))


#: A patch's half-sides for ``sampling.sample_bone``: unused by a burr without a path.
_NO_PATCH = (0.0, 0.0, 0.0)


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
def _sample_corner(vert, j, k, rho, z, cpv, spv, density, swept, labels, us_tab, usk_tab,
                   brick_bone, cx, cy, cz, geo, hx, hy, hz, profile, cache, o0, o1, o2, tick):
    """Sample the bone at corner (j, k) of the burr grid into ``vert[j, k]``."""
    n1 = rho * cpv
    n2 = rho * spv
    px = cx + n1 * geo[0] + n2 * geo[3] + z * geo[6]
    py = cy + n1 * geo[1] + n2 * geo[4] + z * geo[7]
    pz = cz + n1 * geo[2] + n2 * geo[5] + z * geo[8]
    frac, us_f, usk_f, _, _, _ = sample_bone_revolved(
        density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx, hy, hz, cx, cy,
        cz, profile, geo, cache, o0, o1, o2, tick)
    vert[j, k, 0] = frac
    vert[j, k, 1] = us_f
    vert[j, k, 2] = usk_f


@hot_kernel
def cut_voxels_revolved(elem, ds, sub, ds_sub, cos_p, sin_p, d_phi, cos_sub_p, sin_sub_p,
                        corner_tables, profile, geo, centre, v_feed, omega,
                        cutting, ratios, density, swept, labels, us_tab, usk_tab,
                        brick_bone, spacing, vert, acc, out, cache, tick):
    """Cutting force of a burr of revolution against the voxel bone, in the grid frame.

    Args:
        elem, ds, sub, ds_sub, cos_p, sin_p, d_phi, cos_sub_p, sin_sub_p: the burr's
            ``RevolvedGrid`` tables (shapes there).
        profile: (n_seg, 9) the exact profile (``carve_revolved.profile_table``).
        corner_tables: the tuple (corners, cos_pv, sin_pv): corners (2, n_s + 1) ρ, z of
            the element boundaries, mm; cos_pv, sin_pv (n_phi,) sector edges
            (``revolved_corners``). One argument: see ``hot_kernel``'s 30-argument limit.
        geo: (N_GEO,) this tick's tool basis and the shape's bounds
            (``carve_revolved.fill_geometry``).
        centre, v_feed: (3,) reference centre (mm) and feed (mm/s), grid frame.
        omega: signed spindle speed along the axis, rad/s.  cutting: fast enough to cut.
        ratios: the tuple (kn, kg, material_k): the cutter's normal and edge ratios
            (``shapes.Cutter.force_ratios``), and whether each material's K (``usk_tab``) is
            the normal ratio instead of ``kn`` (an abrasive burr).
        density, swept, labels: uint8 voxels; us_tab, usk_tab: (256,) Us and Us·K per label.
        brick_bone: int32 brick counts.  spacing: (3,) voxel size, mm.
        vert: float64 scratch (n_s + 1, n_phi, 3) (corner samples).
        acc: (N_ACC,) scratch; out: (N_OUT,) result (``model.kernels.OUT_*``, grid frame).
        cache, tick: the tick's coverage cache (``carve_revolved.cached_revolved_coverage``).
    """
    corners, cos_pv, sin_pv = corner_tables
    kn, kg, material_k = ratios
    for n in range(N_ACC):
        acc[n] = 0.0
    for n in range(N_OUT):
        out[n] = 0.0
    hx, hy, hz, cx, cy, cz = spacing_and_point(spacing, centre)
    e1x, e1y, e1z = geo[0], geo[1], geo[2]
    e2x, e2y, e2z = geo[3], geo[4], geo[5]
    e3x, e3y, e3z = geo[6], geo[7], geo[8]
    v1, v2, v3 = in_tool_frame(v_feed, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    has_feed = v1 * v1 + v2 * v2 + v3 * v3 > 0.0
    sample_all = not (cutting and has_feed)  # contact needs every element
    abs_omega = abs(omega)
    spin_sign = 1.0 if omega >= 0.0 else -1.0
    w_unit = d_phi / abs_omega if cutting else 0.0
    o0, o1, o2 = cache_origin(cache, cx, cy, cz, hx, hy, hz)
    n_s = ds.shape[0]
    n_phi = cos_p.shape[0]
    m = cos_sub_p.shape[0]
    mf = float(m)
    # Pass 1: which corners an evaluated element needs, and their samples.
    mark_needed(vert, elem[_NR], elem[_NZ], cos_p, sin_p, v1, v2, v3, sample_all)
    # Two levels, as force.cut_voxels: first the corners of even (j, k), the last ring and the
    # rings on the axis; then the others only where their coarse neighbours differ.
    for j in range(n_s + 1):
        rho = corners[0, j]
        z = corners[1, j]
        if rho == 0.0:
            # One point for the whole ring: sampled once if any element there needs it.
            any_needed = False
            for k in range(n_phi):
                if vert[j, k, 0] == PENDING:
                    any_needed = True
            if any_needed:
                _sample_corner(vert, j, 0, rho, z, cos_pv[0], sin_pv[0], density, swept,
                               labels, us_tab, usk_tab, brick_bone, cx, cy, cz, geo, hx, hy,
                               hz, profile, cache, o0, o1, o2, tick)
                for k in range(1, n_phi):
                    for q in range(3):
                        vert[j, k, q] = vert[j, 0, q]
            continue
        if (j & 1) == 1 and j < n_s:
            continue
        for k in range(0, n_phi, 2):
            if vert[j, k, 0] == PENDING:
                _sample_corner(vert, j, k, rho, z, cos_pv[k], sin_pv[k], density, swept,
                               labels, us_tab, usk_tab, brick_bone, cx, cy, cz, geo, hx, hy,
                               hz, profile, cache, o0, o1, o2, tick)
    # The rings on the axis were sampled whole above: no fine corners there. Unneeded corners
    # read as no bone from here.
    for j in range(n_s + 1):
        for k in range(n_phi):
            if not settle_fine(vert, j, k, n_s, n_phi):
                continue
            _sample_corner(vert, j, k, corners[0, j], corners[1, j], cos_pv[k], sin_pv[k],
                           density, swept, labels, us_tab, usk_tab, brick_bone, cx, cy, cz,
                           geo, hx, hy, hz, profile, cache, o0, o1, o2, tick)
    gsx = 0.0
    gsy = 0.0
    gsz = 0.0
    nsum1 = 0.0
    nsum2 = 0.0
    nsum3 = 0.0
    # Pass 2: integrate the elements.
    for k in range(n_phi):
        k1 = k + 1 if k + 1 < n_phi else 0
        cp = cos_p[k]
        sp = sin_p[k]
        vu = v1 * cp + v2 * sp
        for j in range(n_s):
            nr = elem[_NR, j]
            nz = elem[_NZ, j]
            vn = nr * vu + nz * v3
            faces = cutting and vn > 0.0
            if not faces and not sample_all:
                continue
            b00 = vert[j, k, 0]
            b10 = vert[j + 1, k, 0]
            b01 = vert[j, k1, 0]
            b11 = vert[j + 1, k1, 0]
            hi = max(max(b00, b10), max(b01, b11))
            if hi <= 0.0:
                continue
            lo = min(min(b00, b10), min(b01, b11))
            rho = elem[_RHO, j]
            if hi - lo <= SMOOTH_SPREAD:
                # The bone varies little across the element: the corner mean is its integral.
                area = rho * ds[j] * d_phi * 0.25 * (b00 + b10 + b01 + b11)
                acc[11] += area
                nsum1 += area * nr * cp
                nsum2 += area * nr * sp
                nsum3 += area * nz
                if faces:
                    us_f = 0.25 * (vert[j, k, 1] + vert[j + 1, k, 1] + vert[j, k1, 1]
                                   + vert[j + 1, k1, 1])
                    scale = w_unit * ds[j] * vn
                    ft = scale * us_f
                    if material_k:
                        fn = scale * 0.25 * (vert[j, k, 2] + vert[j + 1, k, 2]
                                             + vert[j, k1, 2] + vert[j + 1, k1, 2])
                    else:
                        fn = kn * ft
                    accumulate_forces_revolved(acc, ft, fn, spin_sign * kg * ft, area, vn, rho,
                                               elem[_Z, j], nr, nz, elem[_TR, j], elem[_TZ, j],
                                               cp, sp, abs_omega * rho, spin_sign)
                continue
            # The bone's surface crosses this element: integrate it on m×m sub-elements.
            count_before = acc[8]
            for ia in range(m):
                rho2 = sub[_RHO, j, ia]
                z2 = sub[_Z, j, ia]
                nr2 = sub[_NR, j, ia]
                nz2 = sub[_NZ, j, ia]
                w_area = rho2 * ds_sub[j] * d_phi / mf
                for ib in range(m):
                    cp2 = cp * cos_sub_p[ib] - sp * sin_sub_p[ib]
                    sp2 = sp * cos_sub_p[ib] + cp * sin_sub_p[ib]
                    r1 = rho2 * cp2
                    r2 = rho2 * sp2
                    px = cx + r1 * e1x + r2 * e2x + z2 * e3x
                    py = cy + r1 * e1y + r2 * e2y + z2 * e3y
                    pz = cz + r1 * e1z + r2 * e2z + z2 * e3z
                    frac, us_f, usk_f, gx, gy, gz = sample_bone_revolved(
                        density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx,
                        hy, hz, cx, cy, cz, profile, geo, cache, o0, o1, o2, tick)
                    if frac <= 0.0:
                        continue
                    area = w_area * frac
                    acc[11] += area
                    nsum1 += area * nr2 * cp2
                    nsum2 += area * nr2 * sp2
                    nsum3 += area * nz2
                    gsx += w_area * gx
                    gsy += w_area * gy
                    gsz += w_area * gz
                    vn2 = nr2 * (v1 * cp2 + v2 * sp2) + nz2 * v3
                    if cutting and vn2 > 0.0:
                        scale = w_unit * ds_sub[j] / mf * vn2
                        ft = scale * us_f
                        fn = scale * usk_f if material_k else kn * ft
                        accumulate_forces_revolved(
                            acc, ft, fn, spin_sign * kg * ft, area, vn2, rho2, z2, nr2, nz2,
                            sub[_TR, j, ia], sub[_TZ, j, ia], cp2, sp2, abs_omega * rho2,
                            spin_sign)
            if acc[8] > count_before:  # a refined element counts once
                acc[8] = count_before + 1.0
    g_norm = math.sqrt(gsx * gsx + gsy * gsy + gsz * gsz)
    if g_norm > 0.0:
        # The density grows into the bone: the outward normal is against its gradient.
        acc[12] = -gsx / g_norm
        acc[13] = -gsy / g_norm
        acc[14] = -gsz / g_norm
    else:
        wx = nsum1 * e1x + nsum2 * e2x + nsum3 * e3x
        wy = nsum1 * e1y + nsum2 * e2y + nsum3 * e3y
        wz = nsum1 * e1z + nsum2 * e2z + nsum3 * e3z
        w_norm = math.sqrt(wx * wx + wy * wy + wz * wz)
        if w_norm > 0.0:
            acc[12] = -wx / w_norm
            acc[13] = -wy / w_norm
            acc[14] = -wz / w_norm
    finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out)


@dataclass(frozen=True, eq=False)
class RevolvedTables:
    """What a tick of a burr other than the round abrasive one needs beside the engine's
    buffers: its grid (``RevolvedGrid``), element corners (:func:`revolved_corners`),
    profile (``carve_revolved.profile_table``) and its bounds (``shape_bounds``), the cutter's
    force ratios and scratch."""

    burr: Burr
    grid: RevolvedGrid
    corners: np.ndarray
    cos_pv: np.ndarray
    sin_pv: np.ndarray
    profile: np.ndarray
    bounds: np.ndarray
    normal_ratio: float
    edge_ratio: float
    material_k: bool
    vert: np.ndarray
    geo: np.ndarray
    shaft_base: np.ndarray

    @classmethod
    def build(cls, burr: Burr, k: float, n_elements: int, refine: int) -> RevolvedTables:
        grid = RevolvedGrid.build(burr, n_elements, refine)
        corners, cos_pv, sin_pv = revolved_corners(burr, grid)
        normal, edge = burr.cutter.force_ratios(k)
        return cls(burr, grid, corners, cos_pv, sin_pv, profile_table(grid.segments),
                   shape_bounds(burr), float(normal), float(edge),
                   isinstance(burr.cutter, Abrasive),
                   np.empty((grid.n_s + 1, grid.n_phi, 3)), np.zeros(N_GEO), np.zeros(3))
