"""Carving: the spinning burr sweeps the voxels it covers, with partial-volume accuracy."""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from .bricks import BRICK, BRICK_SHIFT
from .voxels import cache_origin, cached_coverage, sphere_reach, voxel_span

# Layout of the float64 contact vector the carving kernel fills (length N_TOUCH).
TOUCH_FORBIDDEN = 0  # forbidden voxels holding bone that the burr overlaps
TOUCH_VISITED = 1  # voxels examined (cost statistics)
TOUCH_BRICKS = 2  # bricks whose bone changed
TOUCH_NEAR_BONE = 3  # 1 if any brick holding bone lies within the burr's reach
N_TOUCH = 4


@hot_kernel
def carve_sphere(density, swept, labels, forbidden, brick_bone, brick_full, brick_version,
                 brick_forbidden, spacing, centre, previous, radius, carve, version_next,
                 removed, touch, touched, cache, tick):
    """Sweep the voxels a burr sphere covers (one call per tick).

    Raises each covered voxel's ``swept`` to its coverage (never lowers it; air, density 0,
    straight to 255: the force reads of air only whether a burr reached it), adds the bone
    this removed to ``removed[label]`` (units: density × swept steps, i.e. 255² per voxel
    volume), keeps the brick counts exact and stamps changed bricks with ``version_next``.
    With ``carve`` False nothing is written: the call only reports contact (a burr that is not
    spinning fast enough touches but does not cut).

    Args:
        density, swept, labels: uint8 voxel arrays (nx, ny, nz).
        forbidden: uint8 (256,), 1 for labels whose contact is recorded.
        brick_bone, brick_full: int32 brick counts; brick_version: int64 per brick.
        brick_forbidden: uint8 per brick, 1 where a forbidden label holds bone.
        spacing: (3,) voxel size, mm.  centre: (3,) burr centre, grid frame, mm.
        previous: (3,) where the same burr last carved, or NaN. A voxel no farther from there
            than from ``centre`` cannot gain coverage, so it is skipped (a burr at rest
            carves nothing); bricks holding forbidden labels are always checked for contact.
        radius: burr radius, mm.
        removed: float64 (256,), accumulated.  touch: float64 (N_TOUCH,), overwritten.
        touched: float64 (256, 4): per forbidden label touched this tick, its most-covered
            voxel's coverage (column 0; 0 = not touched) and centre (columns 1–3, grid mm).
        cache, tick: the tick's coverage cache (``voxels.cached_coverage``), filled here.

    Returns:
        True if any bone was removed.
    """
    for n in range(N_TOUCH):
        touch[n] = 0.0
    for n in range(touched.shape[0]):
        touched[n, 0] = 0.0
    hx = spacing[0]
    hy = spacing[1]
    hz = spacing[2]
    inv_hz = 1.0 / hz
    cx = centre[0]
    cy = centre[1]
    cz = centre[2]
    nx, ny, nz = density.shape
    r_in2, r_out2 = sphere_reach(radius, hx, hy, hz)
    r_out = math.sqrt(r_out2)
    # The force samples voxels up to one voxel beyond the burr's coverage (the trilinear
    # stencil): bone that close switches the force stage on, so it starts continuously.
    near = r_out + max(hx, max(hy, hz))
    near2 = near * near
    i_lo, i_hi = voxel_span(cx - near, cx + near, hx, nx)
    j_lo, j_hi = voxel_span(cy - near, cy + near, hy, ny)
    k_lo, k_hi = voxel_span(cz - near, cz + near, hz, nz)
    any_removed = False
    visited = 0
    o0, o1, o2 = cache_origin(cache, cx, cy, cz, hx, hy, hz)
    # Half-space of points closer to ``previous`` than to ``centre``: (x − mid)·Δ ≤ 0.
    has_prev = carve and previous[0] == previous[0]
    qx = cx - previous[0] if has_prev else 0.0
    qy = cy - previous[1] if has_prev else 0.0
    qz = cz - previous[2] if has_prev else 0.0
    q0 = 0.5 * (qx * (cx + previous[0]) + qy * (cy + previous[1]) + qz * (cz + previous[2])) \
        if has_prev else 0.0
    # The half-space along a row is q_row + qzh·k > 0, cut at k = −q_row / qzh. Where qzh is
    # too small for a finite reciprocal (a subnormal qz underflowed it to 0: a division by
    # zero in the tick) the row is not cut at all: skipping is only a saving, and keeping
    # voxels that cannot gain costs their visit, nothing else.
    qzh = qz * hz
    inv_qzh = 1.0 / qzh if abs(qzh) > 1e-300 else 0.0
    # Every voxel inside ``previous``'s inner sphere was swept through (255) by that carve,
    # directly or, where its half-space skipped the voxel, by an earlier one no farther from
    # it. Shrunk by far more than the rounding of either test, so a voxel on the boundary is
    # read as before.
    px = previous[0] if has_prev else 0.0
    py = previous[1] if has_prev else 0.0
    pz = previous[2] if has_prev else 0.0
    r_in2_prev = r_in2 * (1.0 - 1e-9)
    for bi in range(i_lo >> BRICK_SHIFT, (i_hi >> BRICK_SHIFT) + 1):
        a0 = max(bi * BRICK, i_lo)
        a1 = min(bi * BRICK + BRICK - 1, i_hi)
        ex = _axis_gap(cx, a0 * hx, a1 * hx)
        fx = max(abs(cx - a0 * hx), abs(cx - a1 * hx))
        for bj in range(j_lo >> BRICK_SHIFT, (j_hi >> BRICK_SHIFT) + 1):
            b0 = max(bj * BRICK, j_lo)
            b1 = min(bj * BRICK + BRICK - 1, j_hi)
            ey = _axis_gap(cy, b0 * hy, b1 * hy)
            fy = max(abs(cy - b0 * hy), abs(cy - b1 * hy))
            for bk in range(k_lo >> BRICK_SHIFT, (k_hi >> BRICK_SHIFT) + 1):
                if brick_bone[bi, bj, bk] == 0:
                    continue
                c0 = max(bk * BRICK, k_lo)
                c1 = min(bk * BRICK + BRICK - 1, k_hi)
                ez = _axis_gap(cz, c0 * hz, c1 * hz)
                ez2 = ez * ez
                gap2 = ex * ex + ey * ey + ez2
                if gap2 >= near2:
                    continue
                touch[TOUCH_NEAR_BONE] = 1.0
                if gap2 >= r_out2:
                    continue
                skip_old = has_prev and brick_forbidden[bi, bj, bk] == 0
                if skip_old and (max(qx * a0 * hx, qx * a1 * hx) + max(qy * b0 * hy, qy * b1 * hy)
                                 + max(qz * c0 * hz, qz * c1 * hz)) <= q0:
                    continue
                fz = max(abs(cz - c0 * hz), abs(cz - c1 * hz))
                inside = fx * fx + fy * fy + fz * fz <= r_in2
                brick_changed = False
                for i in range(a0, a1 + 1):
                    # A slab of rows wholly closer to ``previous`` is skipped at once, not row
                    # by row (the brick test above already drops most of them).
                    if skip_old and (qx * i * hx + max(qy * b0 * hy, qy * b1 * hy)
                                     + max(qz * c0 * hz, qz * c1 * hz)) <= q0:
                        continue
                    dx = i * hx - cx
                    if dx * dx + ey * ey + ez2 >= r_out2:
                        continue  # the slab's rows all pass beside the burr in this brick
                    for j in range(b0, b1 + 1):
                        dy = j * hy - cy
                        k_from = c0
                        k_to = c1
                        if skip_old:
                            # Keep only k with q_row + qz·k·hz > 0 (closer to ``centre``),
                            # before the row's square root: rows wholly behind cost nothing.
                            q_row = qx * i * hx + qy * j * hy - q0
                            # Where the half-space crosses the row, clamped to the grid: a
                            # step almost level in z puts it far away, beyond what converts to
                            # an int.
                            k_cut = min(max(-q_row * inv_qzh, -1.0), float(nz))
                            if inv_qzh > 0.0:
                                k_from = max(k_from, math.floor(k_cut) + 1)
                            elif inv_qzh < 0.0:
                                k_to = min(k_to, math.ceil(k_cut) - 1)
                            elif qz == 0.0 and q_row <= 0.0:
                                continue
                            if k_from > k_to:
                                continue
                        rest = r_out2 - dx * dx - dy * dy
                        if rest <= ez2:
                            # The row's chord of the burr ends short of this brick's part of
                            # the row (most rows near the burr's rim, in a cut's bone bricks).
                            continue
                        reach_z = math.sqrt(rest)
                        k_first = max(k_from, math.ceil((cz - reach_z) * inv_hz))
                        k_last = min(k_to, math.floor((cz + reach_z) * inv_hz))
                        if skip_old:
                            # Both ends inside ``previous``'s inner sphere: so is the whole row
                            # (convex), which that carve swept through. Its run of 255 is
                            # skipped unread.
                            rest_in = r_in2_prev - (i * hx - px) ** 2 - (j * hy - py) ** 2
                            if ((k_first * hz - pz) ** 2 < rest_in
                                    and (k_last * hz - pz) ** 2 < rest_in):
                                continue
                        for k in range(k_first, k_last + 1):
                            # Unsigned: numba then omits the negative-index wraparound, 3 of the
                            # 12 instructions a swept-through voxel costs (thousands a tick).
                            old = swept[i, j, np.uint64(k)]
                            if old == 255:
                                continue  # swept through: nothing left to take or touch
                            visited += 1
                            cq = 255 if inside else cached_coverage(
                                cache, o0, o1, o2, tick, i, j, k, dx, dy, k * hz - cz, radius,
                                hx, hy, hz, r_in2, r_out2)
                            if cq == 0:
                                continue
                            if apply_coverage(density, swept, labels, forbidden, removed, touch,
                                              touched, brick_full, brick_bone, bi, bj, bk, i, j,
                                              k, hx, hy, hz, old, cq, carve):
                                brick_changed = True
                if brick_changed:
                    brick_version[bi, bj, bk] = version_next
                    touch[TOUCH_BRICKS] += 1.0
                    any_removed = True
    touch[TOUCH_VISITED] = visited
    return any_removed


@hot_inline
def apply_coverage(density, swept, labels, forbidden, removed, touch, touched, brick_full,
                   brick_bone, bi, bj, bk, i, j, k, hx, hy, hz, old, cq, carve):
    """One voxel's update by a burr covering ``cq`` (1–255) of it, shared by every burr's
    carve: records contact with a forbidden label, raises ``swept`` from ``old`` (bone to the
    coverage, with its removal and brick (bi, bj, bk)'s counts; air straight to 255) when
    ``carve``. Returns True if bone was removed."""
    d = density[i, j, k]
    if d != 0 and forbidden[labels[i, j, k]] != 0:
        lab = labels[i, j, k]
        touch[TOUCH_FORBIDDEN] += 1.0
        if cq > touched[lab, 0]:
            touched[lab, 0] = cq
            touched[lab, 1] = i * hx
            touched[lab, 2] = j * hy
            touched[lab, 3] = k * hz
    if not carve:
        return False
    if d == 0:
        # Air keeps only whether a burr reached it (what the force's path gate reads):
        # marked swept through at once, it is not covered again every tick the burr passes.
        swept[i, j, k] = 255
        return False
    if cq <= old:
        return False
    swept[i, j, k] = cq
    removed[labels[i, j, k]] += float(d) * float(cq - old)
    if old == 0 and d == 255:
        brick_full[bi, bj, bk] -= 1
    if cq == 255:
        brick_bone[bi, bj, bk] -= 1
    return True


@hot_kernel
def _axis_gap(c, lo, hi):
    """Distance from c to the interval [lo, hi] along one axis."""
    if c < lo:
        return lo - c
    if c > hi:
        return c - hi
    return 0.0
