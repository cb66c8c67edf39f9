"""The cutting force of a burr against a voxel bone (one call per tick), for every burr.

The same model as the flat workpiece (model.md): elements on the burr's surface, a grid of
rows along its profile and sectors about the spin axis, each weighted by the cancelled
dA/|v_t| and by its share of bone. Here the share comes from the voxels
(``sampling.sample_bone``): the original density, trilinear, times the share of the
surroundings no other burr position has swept. Elements whose four corners agree are
integrated from their corners; an element the bone's surface crosses is integrated on m×m
sub-elements, so the interpolated density ramp is averaged rather than point-sampled — that
keeps the bone's volume, and therefore the force, unbiased.

What depends on the burr's shape (its elements' geometry and force, the blend between the two
rules, the normal's fallback) comes from ``force_hooks``, chosen by the type of the burr's
tables at compile time.
"""

from __future__ import annotations

import math

from ..hot_kernel import hot_inline, hot_kernel
from ..model.kernels import N_ACC, N_OUT, finish, in_tool_frame, rotated
from .force_hooks import (
    ACC_NORMALS,
    PENDING,
    UNNEEDED,
    element_area,
    element_force,
    force_frame,
    force_setup,
    normal_direction,
    refined_share,
    ring_on_axis,
    sample_corner,
    sub_element,
    sub_row,
)
from .voxels import cache_origin, spacing_and_point


@hot_kernel
def cut_voxels(burr, centre, axis, v_feed, omega, cutting, density, swept, labels, us_tab,
               usk_tab, brick_bone, spacing, vert, acc, out, cache, tick):
    """Cutting force of the burr against the voxel bone, in the grid frame.

    Args:
        burr: the burr's tables (``tick_tables.SphereTick`` or ``RevolvedTick``; a revolved
            burr's ``geo`` filled this tick by the carve stage).
        centre, axis, v_feed: (3,) grid frame: the burr's (reference) centre (mm), the unit
            tool axis, the feed (mm/s).
        omega: signed spindle speed along the axis, rad/s.  cutting: fast enough to cut.
        density, swept, labels: uint8 voxels; us_tab, usk_tab: (256,) Us and Us·K per label.
        brick_bone: int32 brick counts.  spacing: (3,) voxel size, mm.
        vert: float64 scratch of shape (n_rows + 1, n_phi, 3) (corner samples).
        acc: (N_ACC,) scratch; out: (N_OUT,) result (``model.kernels.OUT_*``, grid frame).
        cache, tick: the tick's coverage cache (``voxels.cached_coverage``).
    """
    for n in range(N_ACC):
        acc[n] = 0.0
    for n in range(N_OUT):
        out[n] = 0.0
    hx, hy, hz, cx, cy, cz = spacing_and_point(spacing, centre)
    basis = force_frame(burr, axis)
    e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z = basis
    v1, v2, v3 = in_tool_frame(v_feed, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z)
    feed_speed = math.sqrt(v1 * v1 + v2 * v2 + v3 * v3)
    has_feed = v1 * v1 + v2 * v2 + v3 * v3 > 0.0
    has_cut = cutting and has_feed
    sample_all = not has_cut  # contact needs every element
    abs_omega = abs(omega)
    spin_sign = 1.0 if omega >= 0.0 else -1.0
    motion = (v1, v2, v3, cutting, abs_omega, spin_sign)
    bone = (density, swept, labels, us_tab, usk_tab, brick_bone)
    spot = (hx, hy, hz, cx, cy, cz)
    reach, interior, rows, consts = force_setup(burr, omega, cutting, has_cut, feed_speed,
                                                bone, spot)
    o0, o1, o2 = cache_origin(cache, cx, cy, cz, hx, hy, hz)
    cached = (cache, o0, o1, o2, tick)
    row_nr, row_nz = rows
    cos_p = burr.cos_p
    sin_p = burr.sin_p
    n_rows = row_nr.shape[0]
    n_phi = cos_p.shape[0]
    m = burr.cos_sub_p.shape[0]
    # Pass 1: sample the bone once at every element corner that an evaluated element needs,
    # in two levels: first the corners with even (j, k) (and the last ring, and the rings on
    # the axis, one point each), then the others only where their coarse neighbours differ.
    # Bone uniform over a coarse cell costs a quarter of the samples (air is always sampled;
    # in a groove's cutting zone few cells are uniform: ~20 of ~430 fine corners a tick).
    # Until it is settled (pass 1b) a corner holds PENDING or UNNEEDED in channel 0.
    mark_needed(vert, row_nr, row_nz, cos_p, sin_p, v1, v2, v3, sample_all)
    for j in range(n_rows + 1):
        on_axis, needed = ring_on_axis(burr, vert, j, n_rows, n_phi)
        if on_axis:
            if needed:
                sample_corner(burr, consts, reach, vert, j, 0, bone, spot, basis, cached,
                              interior)
            for k in range(1, n_phi):
                for q in range(3):
                    vert[j, k, q] = vert[j, 0, q]
            continue
        if (j & 1) == 1 and j < n_rows:
            continue
        for k in range(0, n_phi, 2):
            if vert[j, k, 0] == PENDING:
                sample_corner(burr, consts, reach, vert, j, k, bone, spot, basis, cached,
                              interior)
    # Pass 1b: the fine corners, copied where the bone is uniform around them, else sampled;
    # the unneeded ones read as no bone. Noted: the first and last ring with bone.
    ring_lo = n_rows + 1
    ring_hi = -1
    for j in range(n_rows + 1):
        for k in range(n_phi):
            if settle_fine(vert, j, k, n_rows, n_phi):
                sample_corner(burr, consts, reach, vert, j, k, bone, spot, basis, cached,
                              interior)
            if vert[j, k, 0] > 0.0:
                ring_lo = min(ring_lo, j)
                ring_hi = j
    # The outward surface normal's sums: the density gradient where the bone's surface
    # crosses the burr (grid frame), the area-weighted normals of the elements in bone (tool
    # frame).
    # Pass 2: integrate the elements, in the rows between those rings (the others have no
    # bone at any corner: the loop would skip each of their elements).
    for k in range(n_phi):
        k1 = k + 1 if k + 1 < n_phi else 0
        cp = cos_p[k]
        sp = sin_p[k]
        vu = v1 * cp + v2 * sp
        for j in range(max(ring_lo - 1, 0), min(ring_hi + 1, n_rows)):
            nr = row_nr[j]
            nz = row_nz[j]
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
            refined = refined_share(burr, hi - lo)  # the sub-elements' share of the element
            count_before = acc[8]
            if refined < 1.0:
                # The bone varies little across the element: the corner mean (trapezoid rule)
                # is its integral.
                share = 1.0 - refined
                w_area = element_area(burr, consts, j, nr) * share
                area = w_area * 0.25 * (b00 + b10 + b01 + b11)
                acc[11] += area
                acc[ACC_NORMALS] += area * nr * cp
                acc[ACC_NORMALS + 1] += area * nr * sp
                acc[ACC_NORMALS + 2] += area * nz
                if faces:
                    element_force(burr, consts, acc, vert, j, k, k1, share, area, vn, nr, nz,
                                  cp, sp, motion)
                if refined == 0.0:
                    continue
            # The bone's surface crosses this element: integrate it on m×m sub-elements.
            for a in range(m):
                row = sub_row(burr, consts, j, a, nr, nz, refined)
                for b in range(m):
                    cp2, sp2 = rotated(cp, sp, burr.cos_sub_p[b], burr.sin_sub_p[b])
                    sub_element(burr, consts, reach, acc, j, row, cp2, sp2, refined, bone, spot,
                                basis, cached, motion, interior)
            if acc[8] > count_before:  # a refined element counts once
                acc[8] = count_before + 1.0
    # The density grows into the bone: the outward normal is against its gradient.
    wx, wy, wz = normal_direction(burr, acc, basis)
    w_norm = math.sqrt(wx * wx + wy * wy + wz * wz)
    if w_norm > 0.0:
        acc[12] = -wx / w_norm
        acc[13] = -wy / w_norm
        acc[14] = -wz / w_norm
    finish(acc, e1x, e1y, e1z, e2x, e2y, e2z, e3x, e3y, e3z, v_feed, out)


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
