"""The cutting force of a spherical burr against a voxel bone (one call per tick).

The same model as the flat workpiece (model.md): elements on a latitude/longitude grid about the
spin axis, the cancelled weight dA/|v_t| = R·dθ·dφ/ω, each element's share of bone. Here the
share comes from the voxels (``voxels.sample_bone``): the original density, trilinear, times
the share of the surroundings no other burr position has swept. Elements whose four corners
agree are integrated from their corners; an element the bone's surface crosses is integrated on m×m
sub-elements, so the interpolated density ramp is averaged rather than point-sampled — that
keeps the bone's volume, and therefore the force, unbiased.
"""

from __future__ import annotations

import math

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import (
    N_ACC,
    N_OUT,
    accumulate_forces,
    finish,
    in_tool_frame,
    tool_basis,
)
from .cutters import SphereReach
from .sampling import sample_bone
from .voxels import cache_origin, spacing_and_point, sphere_reach, stencils_inside

#: Elements whose corner fractions differ by more than this are integrated on sub-elements.
#: A crossing bone surface makes them differ by ~1; smooth partial availability (the sides of
#: the groove the burr is ploughing) by a few per cent, where the corner mean is exact enough.
SMOOTH_SPREAD = 0.25
#: Between these spreads an element is integrated both ways and the two blended smoothly: a
#: switch at SMOOTH_SPREAD stepped the force by the two rules' difference whenever a corner
#: crossed it (plunges: force against depth fell by up to 3 % and removal by 12 % in steps).
BLEND_SPREAD_LO = 0.2
BLEND_SPREAD_HI = 0.3
#: The surface normal is −(G·|G| + FALLBACK·N), G = Σ w·∇ρ over the patches the original
#: surface crosses (mm), N = Σ area·n over the patches in bone (mm²): the density gradient
#: wherever the surface crosses the cutting zone, fading continuously into the in-bone
#: normals' mean as it leaves it, instead of switching to it only when no patch is crossed
#: (a few patches left near the zone's edge gave a noisy gradient: the normal force jumped by
#: 45 % in plunges on an oblique grid). Against a groove's G of a few mm the fallback's part
#: is ~1e-7.
FALLBACK = 5e-6
#: Corner markers between the two sampling levels (real fractions are in [0, 1]).
PENDING = -1.0
UNNEEDED = -2.0


@hot_kernel
def cut_voxels(cos_t, sin_t, cos_p, sin_p, d_theta, d_phi, cos_sub_t, sin_sub_t, cos_sub_p,
               sin_sub_p, corner_tables, radius, centre, axis, v_feed, omega,
               cutting, density, swept, labels, us_tab, usk_tab, brick_bone, spacing,
               vert, acc, out, cache, tick, cand):
    """Cutting force of the burr against the voxel bone, in the grid frame.

    Args:
        cos_t … sin_sub_p: the burr tables (``BurrGrid``).  corner_tables: the tuple
            (cos_tv, sin_tv, cos_pv, sin_pv), (n_theta + 1,) twice and (n_phi,) twice, at the
            element corners (one argument: see ``hot_kernel``'s 30-argument limit).
        radius: R, mm.  centre, axis, v_feed: (3,) grid frame (mm, any-length axis, mm/s).
        omega: signed spindle speed along the axis, rad/s.  cutting: fast enough to cut.
        density, swept, labels: uint8 voxels; us_tab, usk_tab: (256,) Us and Us·K per label.
        brick_bone: int32 brick counts.  spacing: (3,) voxel size, mm.
        vert: float64 scratch of shape (n_theta + 1, n_phi, 3) (corner samples).
        acc: (N_ACC,) scratch; out: (N_OUT,) result (``model.kernels.OUT_*``, grid frame).
        cache, tick: the tick's coverage cache (``voxels.cached_coverage``).
        cand: the burr's path near it, with its header (``history.history_candidates``).
    """
    cos_tv, sin_tv, cos_pv, sin_pv = corner_tables
    for n in range(N_ACC):
        acc[n] = 0.0
    for n in range(N_OUT):
        out[n] = 0.0
    hx, hy, hz, cx, cy, cz = spacing_and_point(spacing, centre)
    basis = tool_basis(axis[0], axis[1], axis[2])
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    v1, v2, v3 = in_tool_frame(v_feed, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    has_feed = v1 * v1 + v2 * v2 + v3 * v3 > 0.0
    feed_speed = math.sqrt(v1 * v1 + v2 * v2 + v3 * v3)
    has_cut = cutting and has_feed
    sample_all = not (cutting and has_feed)  # contact needs every element
    abs_omega = abs(omega)
    spin_sign = 1.0 if omega >= 0.0 else -1.0
    w_unit = radius * d_theta * d_phi / abs_omega if cutting else 0.0
    area_unit = radius * radius * d_theta * d_phi
    r_in2, r_out2 = sphere_reach(radius, hx, hy, hz)
    reach = SphereReach(radius, r_in2, r_out2, cand)
    o0, o1, o2 = cache_origin(cache, cx, cy, cz, hx, hy, hz)
    n_theta = cos_t.shape[0]
    n_phi = cos_p.shape[0]
    m = cos_sub_t.shape[0]
    m2 = float(m * m)
    inv_m2 = 1.0 / m2  # the sub-element loop multiplies: divisions queue on one unit
    inv_feed = 1.0 / feed_speed if has_cut else 0.0
    half_t, half_p = patch_half_sides(radius, d_theta, d_phi, m)
    # Every sample lies on the burr's sphere: where all of their stencils are inside the grid
    # (nearly always), no sample checks its own.
    interior = stencils_inside(density.shape[0], density.shape[1], density.shape[2], hx, hy, hz,
                               cx, cy, cz, radius)
    # Pass 1: sample the bone once at every element corner that an evaluated element needs,
    # in two levels: first the corners with even (j, k) (and the last ring), then the others
    # only where their coarse neighbours differ. Bone uniform over a coarse cell costs a
    # quarter of the samples (air is always sampled; in a groove's cutting zone few cells are
    # uniform: ~20 of ~430 fine corners a tick). Until it is settled (pass 1b) a corner holds
    # PENDING or UNNEEDED in channel 0.
    mark_needed(vert, sin_t, cos_t, cos_p, sin_p, v1, v2, v3, sample_all)
    for j in range(n_theta + 1):
        pole = j == 0 or j == n_theta
        if not (pole or (j & 1) == 0):
            continue
        for k in range(n_phi):
            if pole and k > 0:
                for q in range(3):
                    vert[j, k, q] = vert[j, 0, q]
                continue
            if (k & 1) == 1 and not pole:
                continue
            if vert[j, k, 0] == PENDING:
                _sample_corner(reach, vert, j, k, sin_tv[j], cos_tv[j], cos_pv[k], sin_pv[k],
                               density, swept, labels, us_tab, usk_tab, brick_bone, centre,
                               basis, hx, hy, hz, cache, o0, o1, o2, tick, half_t, half_p,
                               interior)
    # Pass 1b: the fine corners, copied where the bone is uniform around them, else sampled;
    # the unneeded ones read as no bone. Noted: the first and last ring with bone.
    ring_lo = n_theta + 1
    ring_hi = -1
    for j in range(n_theta + 1):
        for k in range(n_phi):
            if settle_fine(vert, j, k, n_theta, n_phi):
                _sample_corner(reach, vert, j, k, sin_tv[j], cos_tv[j], cos_pv[k], sin_pv[k],
                               density, swept, labels, us_tab, usk_tab, brick_bone, centre,
                               basis, hx, hy, hz, cache, o0, o1, o2, tick, half_t, half_p,
                               interior)
            if vert[j, k, 0] > 0.0:
                ring_lo = min(ring_lo, j)
                ring_hi = j
    # Outward surface normal: from the density gradient where the bone's surface crosses the
    # burr; failing that, against the mean normal of the elements in bone.
    gsx = 0.0
    gsy = 0.0
    gsz = 0.0
    nsum1 = 0.0
    nsum2 = 0.0
    nsum3 = 0.0
    # Pass 2: integrate the elements, in the rows between those rings (the others have no
    # bone at any corner: the loop would skip each of their elements).
    for k in range(n_phi):
        k1 = k + 1 if k + 1 < n_phi else 0
        cp = cos_p[k]
        sp = sin_p[k]
        vu = v1 * cp + v2 * sp
        for j in range(max(ring_lo - 1, 0), min(ring_hi + 1, n_theta)):
            st = sin_t[j]
            ct = cos_t[j]
            vn = st * vu + ct * v3
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
            refined = 1.0  # the sub-elements' share of this element
            if hi - lo < BLEND_SPREAD_HI:
                refined = 0.0
                if hi - lo > BLEND_SPREAD_LO:
                    x = (hi - lo - BLEND_SPREAD_LO) / (BLEND_SPREAD_HI - BLEND_SPREAD_LO)
                    refined = x * x * (3.0 - 2.0 * x)
            count_before = acc[8]
            if refined < 1.0:
                # The bone varies little across the element: the corner mean (trapezoid rule)
                # is its integral.
                w_area = area_unit * st * (1.0 - refined)
                area = w_area * 0.25 * (b00 + b10 + b01 + b11)
                acc[11] += area
                nsum1 += area * st * cp
                nsum2 += area * st * sp
                nsum3 += area * ct
                if faces:
                    us_f = 0.25 * (vert[j, k, 1] + vert[j + 1, k, 1] + vert[j, k1, 1]
                                   + vert[j + 1, k1, 1])
                    usk_f = 0.25 * (vert[j, k, 2] + vert[j + 1, k, 2] + vert[j, k1, 2]
                                    + vert[j + 1, k1, 2])
                    scale = w_unit * vn * (1.0 - refined)
                    accumulate_forces(acc, scale * us_f, scale * usk_f, area, vn, st, ct, cp,
                                      sp, abs_omega * radius * st, spin_sign, radius)
                if refined == 0.0:
                    continue
            # The bone's surface crosses this element: integrate it on m×m sub-elements.
            for a in range(m):
                ct2 = ct * cos_sub_t[a] - st * sin_sub_t[a]
                st2 = st * cos_sub_t[a] + ct * sin_sub_t[a]
                for b in range(m):
                    cp2 = cp * cos_sub_p[b] - sp * sin_sub_p[b]
                    sp2 = sp * cos_sub_p[b] + cp * sin_sub_p[b]
                    n1 = st2 * cp2
                    n2 = st2 * sp2
                    px = cx + radius * (n1 * e1x + n2 * e2x + ct2 * e3x)
                    py = cy + radius * (n1 * e1y + n2 * e2y + ct2 * e3y)
                    pz = cz + radius * (n1 * e1z + n2 * e2z + ct2 * e3z)
                    # The sub-element's half-sides along θ and φ (for the path's share).
                    h2 = half_p * st2
                    frac, us_f, usk_f, gx, gy, gz = sample_bone(
                        reach, density, swept, labels, us_tab, usk_tab, brick_bone, px, py,
                        pz, hx, hy, hz, cx, cy, cz, cache, o0, o1, o2, tick,
                        (half_t * (ct2 * cp2 * e1x + ct2 * sp2 * e2x - st2 * e3x),
                         half_t * (ct2 * cp2 * e1y + ct2 * sp2 * e2y - st2 * e3y),
                         half_t * (ct2 * cp2 * e1z + ct2 * sp2 * e2z - st2 * e3z)),
                        (h2 * (cp2 * e2x - sp2 * e1x), h2 * (cp2 * e2y - sp2 * e1y),
                         h2 * (cp2 * e2z - sp2 * e1z)), interior)
                    if frac <= 0.0:
                        continue
                    w_area = area_unit * st2 * inv_m2 * refined
                    area = w_area * frac
                    acc[11] += area
                    nsum1 += area * n1
                    nsum2 += area * n2
                    nsum3 += area * ct2
                    vn2 = n1 * v1 + n2 * v2 + ct2 * v3
                    # Weighted by how fast the patch cuts: a crossing that slides out of the
                    # cutting zone (where n·v_f → 0) fades out of the estimate instead of
                    # leaving it as a few noisy gradients.
                    w_grad = w_area * (max(vn2, 0.0) * inv_feed if has_cut else 1.0)
                    gsx += w_grad * gx
                    gsy += w_grad * gy
                    gsz += w_grad * gz
                    if cutting and vn2 > 0.0:
                        scale = w_unit * vn2 * inv_m2 * refined
                        accumulate_forces(acc, scale * us_f, scale * usk_f, area, vn2, st2, ct2,
                                          cp2, sp2, abs_omega * radius * st2, spin_sign,
                                          radius)
            if acc[8] > count_before:  # a refined element counts once
                acc[8] = count_before + 1.0
    # The density grows into the bone: the outward normal is against its gradient.
    g_norm = math.sqrt(gsx * gsx + gsy * gsy + gsz * gsz)
    wx = g_norm * gsx + FALLBACK * (nsum1 * e1x + nsum2 * e2x + nsum3 * e3x)
    wy = g_norm * gsy + FALLBACK * (nsum1 * e1y + nsum2 * e2y + nsum3 * e3y)
    wz = g_norm * gsz + FALLBACK * (nsum1 * e1z + nsum2 * e2z + nsum3 * e3z)
    w_norm = math.sqrt(wx * wx + wy * wy + wz * wz)
    if w_norm > 0.0:
        acc[12] = -wx / w_norm
        acc[13] = -wy / w_norm
        acc[14] = -wz / w_norm
    finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out)


@hot_inline
def patch_half_sides(radius, d_theta, d_phi, m):
    """Half-sides of a sub-element (m×m per element of dθ × dφ on a sphere of ``radius`` mm)
    along θ and, per sin θ, along φ, mm: the patch a sample's path share is taken over
    (``history.history_share``); a patch at θ reaches at most their sum."""
    return 0.5 * radius * d_theta / m, 0.5 * radius * d_phi / m


@hot_inline
def _sample_corner(reach, vert, j, k, st, ct, cpv, spv, density, swept, labels, us_tab,
                   usk_tab, brick_bone, centre, basis, hx, hy, hz, cache, o0, o1, o2, tick,
                   half_t, half_p, interior):
    """Sample the bone at corner (j, k) of the burr grid into ``vert[j, k]``.

    ``reach``: the burr (``cutters.SphereReach``); ``centre``: (3,) burr centre; ``basis``:
    the tool frame (e1, e2, e3) as 9 floats (``tool_basis``), packed to keep to 30 arguments
    (``hot_kernel``); ``interior``: every sample's stencil lies inside the grid
    (``voxels.stencils_inside``).
    """
    radius = reach.radius
    cx = centre[0]
    cy = centre[1]
    cz = centre[2]
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    n1 = st * cpv
    n2 = st * spv
    px = cx + radius * (n1 * e1x + n2 * e2x + ct * e3x)
    py = cy + radius * (n1 * e1y + n2 * e2y + ct * e3y)
    pz = cz + radius * (n1 * e1z + n2 * e2z + ct * e3z)
    h2 = half_p * st
    frac, us_f, usk_f, _, _, _ = sample_bone(
        reach, density, swept, labels, us_tab, usk_tab, brick_bone, px, py, pz, hx, hy, hz,
        cx, cy, cz, cache, o0, o1, o2, tick,
        (half_t * (ct * cpv * e1x + ct * spv * e2x - st * e3x),
         half_t * (ct * cpv * e1y + ct * spv * e2y - st * e3y),
         half_t * (ct * cpv * e1z + ct * spv * e2z - st * e3z)),
        (h2 * (cpv * e2x - spv * e1x), h2 * (cpv * e2y - spv * e1y), h2 * (cpv * e2z - spv * e1z)),
        interior)
    vert[j, k, 0] = frac
    vert[j, k, 1] = us_f
    vert[j, k, 2] = usk_f


@hot_kernel
def mark_needed(vert, n_rho, n_z, cos_p, sin_p, v1, v2, v3, sample_all):
    """Pass 1a of the corner sampling, shared by every burr shape: mark each corner
    ``vert[j, k, 0]`` PENDING if an element that will be evaluated needs it, else UNNEEDED.

    Args:
        vert: float64 (n_rows + 1, n_phi, 3) corner samples: only channel 0 is written.
        n_rho, n_z: (n_rows,) the element rows' normal across and along the axis (sin θ,
            cos θ on the sphere).  cos_p, sin_p: (n_phi,) sector midpoints.
        v1, v2, v3: the feed in the tool frame, mm/s.  sample_all: every element counts
            (contact needs them all).
    """
    n_rows = n_rho.shape[0]
    n_phi = cos_p.shape[0]
    if sample_all:
        for j in range(n_rows + 1):
            for k in range(n_phi):
                vert[j, k, 0] = PENDING
        return
    for j in range(n_rows + 1):
        # The corner belongs to elements (j−1 | j, k−1 | k); is any facing the feed? Element
        # (j, k) faces it if n_rho[j]·(v1 cos φk + v2 sin φk) + n_z[j]·v3 > 0. Sector k's
        # two elements are tested once, for corners k and k + 1.
        ja = max(j - 1, 0)
        jb = min(j, n_rows - 1)
        st_a = n_rho[ja]
        ct3_a = n_z[ja] * v3
        st_b = n_rho[jb]
        ct3_b = n_z[jb] * v3
        vu = v1 * cos_p[n_phi - 1] + v2 * sin_p[n_phi - 1]
        faces_before = st_a * vu + ct3_a > 0.0 or st_b * vu + ct3_b > 0.0
        for k in range(n_phi):
            vu = v1 * cos_p[k] + v2 * sin_p[k]
            faces = st_a * vu + ct3_a > 0.0 or st_b * vu + ct3_b > 0.0
            vert[j, k, 0] = PENDING if faces or faces_before else UNNEEDED
            faces_before = faces


@hot_inline
def settle_fine(vert, j, k, n_rows, n_phi):
    """Pass 1b of the corner sampling for corner (j, k), once the coarse corners (even j and
    k, the last ring, rings on the axis) are sampled: an UNNEEDED corner reads as no bone; a
    fine corner still PENDING whose coarse cell holds uniform bone (all of its corners
    sampled and identical) takes their value. Returns True if the corner is still PENDING:
    sample it. The checks read coarse corners only, and take UNNEEDED and no bone alike, so
    the corners may be settled and sampled one by one, in any order.

    Args:
        vert: float64 (n_rows + 1, n_phi, 3) corner samples (``mark_needed``).
    """
    v = vert[j, k, 0]
    if v == UNNEEDED:
        vert[j, k, 0] = 0.0
        vert[j, k, 1] = 0.0
        vert[j, k, 2] = 0.0
        return False
    if v != PENDING:
        return False
    fine_row = (j & 1) == 1 and j < n_rows
    jm = j - 1 if fine_row else j
    jp = j + 1 if fine_row else j
    if (k & 1) == 1:
        km = k - 1
        kp = k + 1 if k + 1 < n_phi else 0
    else:
        km = k
        kp = k
    # Air is sampled all the same: bone a coarse cell's corners miss can reach the stencil
    # between them, and air samples are cheap.
    g = vert[jm, km, 0]
    if not (g > 0.0 and vert[jm, kp, 0] == g and vert[jp, km, 0] == g
            and vert[jp, kp, 0] == g):
        return True
    u = vert[jm, km, 1]
    w = vert[jm, km, 2]
    if not (vert[jm, kp, 1] == u and vert[jp, km, 1] == u and vert[jp, kp, 1] == u
            and vert[jm, kp, 2] == w and vert[jp, km, 2] == w and vert[jp, kp, 2] == w):
        return True
    vert[j, k, 0] = g
    vert[j, k, 1] = u
    vert[j, k, 2] = w
    return False
