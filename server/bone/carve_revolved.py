"""How much of a voxel a burr of any shape (a solid of revolution) covers, and where it reaches.

Each voxel's covered share comes from its signed distance to the solid, taken in the tool
frame (ρ, z) against the exact profile segments (``revolved.RevolvedGrid.segments``), with the
voxel's half-extents projected on the distance's gradient (``voxels.plane_fraction``): the
sphere's rule (``voxels.sphere_coverage``) for any profile. The one carve
(``carve.carve_voxels``) walks such a burr's rows with ``cached_row_reach`` and covers with
``cached_revolved_coverage`` (``carve_hooks.RevolvedCarve``); the bone sampler reads the same
coverage back (``cutters.RevolvedReach``).
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import tool_basis
from ..model.shapes import Arc, Burr
from .voxels import CACHE_SHIFT, plane_fraction

# Layout of the float64 per-tick geometry vector (``fill_geometry``), length N_GEO.
GEO_E1 = 0  # [0:3] tool basis e1, grid frame
GEO_E2 = 3  # [3:6] e2
GEO_AXIS = 6  # [6:9] e3 = the unit tool axis
GEO_RHO_MAX = 9  # the profile's largest ρ, mm
GEO_Z_TIP = 10  # z of the tip (lowest), mm
GEO_Z_TOP = 11  # z of the top (highest), mm
GEO_HALF_DIAG = 12  # half a voxel's diagonal, mm
GEO_R_BALL = 13  # the farthest point of the solid from the reference centre, mm
N_GEO = 14
#: The carve's rows are cut to the ball of the solid's farthest point, widened by this share of
#: a voxel against rounding (a voxel there covers nothing: only the cost depends on it).
BALL_SLACK_VOXELS = 1e-6


def bounding_radius_mm(burr: Burr) -> float:
    """Distance from the reference centre to the farthest point of the solid, mm: the
    largest over its profile segments (a line's at an end; an arc's at an end, or where the
    ray from the centre through the arc's centre meets it, if that lies on the arc). The
    carve's rows and the coverage's first reject stop there, and the coverage cache is sized
    like a sphere of this radius."""
    far = 0.0
    for seg in burr.shape.profile():
        if isinstance(seg, Arc):
            psi_lo, psi_hi = sorted((seg.psi0, seg.psi1))
            far = max(far, *(math.hypot(seg.rho_c + seg.r * math.cos(psi),
                                        seg.z_c + seg.r * math.sin(psi))
                             for psi in (psi_lo, psi_hi)))
            centre = math.hypot(seg.rho_c, seg.z_c)
            if centre == 0.0:
                far = max(far, seg.r)
                continue
            away = math.atan2(seg.z_c, seg.rho_c)
            turns = math.floor((psi_lo - away) / (2.0 * math.pi))
            if any(psi_lo <= away + 2.0 * math.pi * n <= psi_hi for n in (turns, turns + 1)):
                far = max(far, centre + seg.r)
        else:
            far = max(far, math.hypot(seg.rho0, seg.z0), math.hypot(seg.rho1, seg.z1))
    return far


def shape_bounds(burr: Burr) -> np.ndarray:
    """(ρ_max, z_tip, z_top, r_ball) of the burr's profile in its tool frame, mm, float64
    (4,); r_ball: ``bounding_radius_mm``. The profiles shapes.py builds run monotonically in
    z from tip to top."""
    profile = burr.shape.profile()
    z_tip = float(profile[0].at(np.array([0.0]))[1][0])
    z_top = float(profile[-1].at(np.array([1.0]))[1][0])
    return np.array([burr.shape.max_radius_mm, z_tip, z_top, bounding_radius_mm(burr)],
                    dtype=np.float64)


@hot_kernel
def fill_geometry(geo, axis, bounds, spacing):
    """This tick's tool basis and the shape's bounds into ``geo`` (N_GEO,)."""
    (geo[0], geo[1], geo[2], geo[3], geo[4], geo[5], geo[6], geo[7],
     geo[8]) = tool_basis(axis[0], axis[1], axis[2])
    geo[GEO_RHO_MAX] = bounds[0]
    geo[GEO_Z_TIP] = bounds[1]
    geo[GEO_Z_TOP] = bounds[2]
    geo[GEO_HALF_DIAG] = 0.5 * math.sqrt(spacing[0] ** 2 + spacing[1] ** 2 + spacing[2] ** 2)
    geo[GEO_R_BALL] = bounds[3]


def profile_table(segments: np.ndarray) -> np.ndarray:
    """The profile (``revolved.RevolvedGrid.segments``) as the distance kernels read it,
    float64 (n_seg, 9): a line as (0, ρ0, z0, Δρ, Δz, |Δ|², n_ρ, n_z, 0), an arc as
    (1, ρc, zc, r, orientation ±1, cos ψlo, sin ψlo, cos ψhi, sin ψhi) with ψlo < ψhi (mm,
    unit vectors). Arcs may span at most a half-circle (every shape in shapes.py)."""
    table = np.zeros((segments.shape[0], 9))
    for i, (kind, a, b, c, d, e) in enumerate(np.asarray(segments, dtype=np.float64)):
        if kind == 0.0:
            dr, dz = c - a, d - b
            length = math.hypot(dr, dz)
            table[i] = (0.0, a, b, dr, dz, length * length, dz / length, -dr / length, 0.0)
            continue
        lo, hi = min(d, e), max(d, e)
        if hi - lo > math.pi + 1e-12:
            raise ValueError(f"a profile arc spans {hi - lo} rad, more than a half-circle")
        table[i] = (1.0, a, b, c, 1.0 if e > d else -1.0, math.cos(lo), math.sin(lo),
                    math.cos(hi), math.sin(hi))
    return table


@hot_kernel
def profile_distance(table, rho, z):
    """Signed distance from (ρ, z) to the solid (negative inside), mm, and its unit gradient
    (g_ρ, g_z); ``table`` as ``profile_table``. The nearest profile point decides; its side
    comes from that segment's outward normal, which is exact for convex profiles whose
    corners turn by at most 90° (every shape in shapes.py: at such a corner any point in the
    normal cone has a non-negative dot with both adjacent normals)."""
    best = math.inf
    sign = 1.0
    gr = 0.0
    gz = 0.0
    for i in range(table.shape[0]):
        if table[i, 0] == 0.0:
            r0 = table[i, 1]
            z0 = table[i, 2]
            dr = table[i, 3]
            dz = table[i, 4]
            l2 = table[i, 5]
            t = ((rho - r0) * dr + (z - z0) * dz) / l2 if l2 > 0.0 else 0.0
            t = min(max(t, 0.0), 1.0)
            qr = r0 + t * dr
            qz = z0 + t * dz
            nr = table[i, 6]
            nz = table[i, 7]
        else:
            rc = table[i, 1]
            zc = table[i, 2]
            r = table[i, 3]
            orient = table[i, 4]
            ur = rho - rc
            uz = z - zc
            length = math.sqrt(ur * ur + uz * uz)
            # Within the arc's angles (a span ≤ π): counter-clockwise of the low end and
            # clockwise of the high end.
            if (length > 0.0 and table[i, 5] * uz - table[i, 6] * ur >= 0.0
                    and ur * table[i, 8] - uz * table[i, 7] >= 0.0):
                cr = ur / length
                cz = uz / length
            else:
                lr = rc + r * table[i, 5] - rho
                lz = zc + r * table[i, 6] - z
                hr = rc + r * table[i, 7] - rho
                hz = zc + r * table[i, 8] - z
                if lr * lr + lz * lz <= hr * hr + hz * hz:
                    cr = table[i, 5]
                    cz = table[i, 6]
                else:
                    cr = table[i, 7]
                    cz = table[i, 8]
            qr = rc + r * cr
            qz = zc + r * cz
            nr = orient * cr
            nz = orient * cz
        wr = rho - qr
        wz = z - qz
        d = math.sqrt(wr * wr + wz * wz)
        if d < best:
            best = d
            side = wr * nr + wz * nz
            sign = -1.0 if side < 0.0 else 1.0
            if d > 1e-12:
                gr = sign * wr / d
                gz = sign * wz / d
            else:
                gr = nr
                gz = nz
    return sign * best, gr, gz


@hot_inline
def revolved_coverage(dx, dy, dz, profile, geo, hx, hy, hz):
    """Fraction of a voxel inside the burr, quantized to 0–255. (dx, dy, dz): voxel centre
    minus the reference centre, mm, grid frame. Within a voxel the solid is taken as its
    tangent plane at the nearest profile point (as ``voxels.sphere_coverage``)."""
    ax = geo[6]
    ay = geo[7]
    az = geo[8]
    half_diag = geo[GEO_HALF_DIAG]
    # Beyond the solid's ball by half a diagonal: at least that far from the solid.
    ball = geo[GEO_R_BALL] + half_diag
    if dx * dx + dy * dy + dz * dz >= ball * ball:
        return 0
    z = dx * ax + dy * ay + dz * az
    if z < geo[GEO_Z_TIP] - half_diag or z > geo[GEO_Z_TOP] + half_diag:
        return 0
    rx = dx - z * ax
    ry = dy - z * ay
    rz = dz - z * az
    rho2 = rx * rx + ry * ry + rz * rz
    reach = geo[GEO_RHO_MAX] + half_diag
    if rho2 >= reach * reach:
        return 0
    rho = math.sqrt(rho2)
    sd, gr, gzz = profile_distance(profile, rho, z)
    if sd >= half_diag:
        return 0
    if sd <= -half_diag:
        return 255
    if rho > 0.0:
        ux = rx / rho
        uy = ry / rho
        uz = rz / rho
    else:
        ux = geo[0]
        uy = geo[1]
        uz = geo[2]
    gx = gr * ux + gzz * ax
    gy = gr * uy + gzz * ay
    gz = gr * uz + gzz * az
    frac = plane_fraction(-sd, 0.5 * hx * abs(gx), 0.5 * hy * abs(gy), 0.5 * hz * abs(gz))
    return int(frac * 255.0 + 0.5)


@hot_inline
def cached_revolved_coverage(cache, o0, o1, o2, tick, i, j, k, dx, dy, dz, profile, geo, hx,
                             hy, hz):
    """``revolved_coverage`` of voxel (i, j, k), computed at most once per tick (the cache's
    stamping as ``voxels.cached_coverage``)."""
    a = i - o0
    b = j - o1
    c = k - o2
    if 0 <= a < cache.shape[0] and 0 <= b < cache.shape[1] and 0 <= c < cache.shape[2]:
        entry = cache[a, b, c]
        if (entry >> CACHE_SHIFT) == tick:
            return entry & 255
        cq = revolved_coverage(dx, dy, dz, profile, geo, hx, hy, hz)
        cache[a, b, c] = (tick << CACHE_SHIFT) | cq
        return cq
    return revolved_coverage(dx, dy, dz, profile, geo, hx, hy, hz)


@hot_inline
def axis_gap(px, py, pz, cx, cy, cz, geo):
    """Distance from p to the burr's axis segment (tip to top), mm."""
    ax = geo[6]
    ay = geo[7]
    az = geo[8]
    t = (px - cx) * ax + (py - cy) * ay + (pz - cz) * az
    t = min(max(t, geo[GEO_Z_TIP]), geo[GEO_Z_TOP])
    qx = px - cx - t * ax
    qy = py - cy - t * ay
    qz = pz - cz - t * az
    return math.sqrt(qx * qx + qy * qy + qz * qz)


@hot_inline
def _row_span(dx, dy, cz, hz, geo, r_out, k_lo, k_hi):
    """The voxels k of the row (dx, dy from the reference centre; z = k·hz) that can be
    covered: inside the cylinder ρ < ``r_out`` about the axis and between the tip's and the
    top's planes widened by half a voxel's diagonal (``revolved_coverage``'s quick reject).
    Returns (first, last); empty when first > last."""
    ax = geo[6]
    ay = geo[7]
    az = geo[8]
    half_diag = geo[GEO_HALF_DIAG]
    w_a = dx * ax + dy * ay - cz * az
    # Along the row the point is w + t·ẑ (t = k·hz, mm): its axial coordinate w·a + t·a_z.
    lo = -math.inf
    hi = math.inf
    z_min = geo[GEO_Z_TIP] - half_diag
    z_max = geo[GEO_Z_TOP] + half_diag
    if abs(az) > 1e-12:
        t0 = (z_min - w_a) / az
        t1 = (z_max - w_a) / az
        lo = max(lo, min(t0, t1))
        hi = min(hi, max(t0, t1))
    elif not z_min <= w_a <= z_max:
        return 1, 0
    # Radial part: |q + t·e|² ≤ r², q = w − (w·a)a, e = ẑ − a_z·a.
    qx = dx - w_a * ax
    qy = dy - w_a * ay
    qz = -cz - w_a * az
    ex = -az * ax
    ey = -az * ay
    ez = 1.0 - az * az
    e2 = ex * ex + ey * ey + ez * ez
    qe = qx * ex + qy * ey + qz * ez
    rest = qx * qx + qy * qy + qz * qz - r_out * r_out
    if e2 > 1e-12:
        disc = qe * qe - e2 * rest
        if disc < 0.0:
            return 1, 0
        root = math.sqrt(disc)
        lo = max(lo, (-qe - root) / e2)
        hi = min(hi, (-qe + root) / e2)
    elif rest > 0.0:
        return 1, 0
    if lo > hi:
        return 1, 0
    # Widened by a hair: a voxel on the bound rounds either way, and it covers nothing there.
    first = -1 if lo == -math.inf else math.ceil(lo / hz - 1e-6)
    last = k_hi + 1 if hi == math.inf else math.floor(hi / hz + 1e-6)
    return max(k_lo, first), min(k_hi, last)


@hot_inline
def row_reach(dx, dy, cz, hz, geo, r_out, ball2, k_lo, k_hi):
    """The voxels k in [k_lo, k_hi] of the row (dx, dy from the reference centre; z = k·hz)
    that the burr can cover: within ``_row_span`` and within the ball of squared radius
    ``ball2`` (mm²) about the reference centre. Returns (first, last); empty when first >
    last."""
    rest = ball2 - dx * dx - dy * dy
    if rest <= 0.0:
        return 1, 0
    reach_z = math.sqrt(rest)
    k_first, k_last = _row_span(dx, dy, cz, hz, geo, r_out, k_lo, k_hi)
    return (max(k_first, math.ceil((cz - reach_z) / hz)),
            min(k_last, math.floor((cz + reach_z) / hz)))


@hot_inline
def cached_row_reach(rows, o0, o1, tick, i, j, dx, dy, cz, hz, geo, r_out, ball2, k_lo, k_hi):
    """``row_reach`` of row (i, j), computed at most once per tick (``rows``: entries
    (tick, first, last) at (i − o0, j − o1), as the coverage cache keeps its own)."""
    a = i - o0
    b = j - o1
    if 0 <= a < rows.shape[0] and 0 <= b < rows.shape[1]:
        if rows[a, b, 0] == tick:
            return rows[a, b, 1], rows[a, b, 2]
        first, last = row_reach(dx, dy, cz, hz, geo, r_out, ball2, k_lo, k_hi)
        rows[a, b, 0] = tick
        rows[a, b, 1] = first
        rows[a, b, 2] = last
        return first, last
    return row_reach(dx, dy, cz, hz, geo, r_out, ball2, k_lo, k_hi)
