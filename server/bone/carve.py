"""Carving: the spinning burr sweeps the voxels it covers, with partial-volume accuracy.

One carve for every burr (``carve_voxels``): it walks the bricks holding bone near the burr,
their rows and voxels, and raises each voxel's swept share to what the burr covers. Where the
walk starts, which bricks and rows it may skip and what a voxel's coverage is depend on the
burr's shape: they are the hooks of ``carve_hooks``, chosen by the type of the ``cutter``
tuple (``carve_hooks.SphereCarve``, ``carve_hooks.RevolvedCarve``) when the carve compiles.
"""

from __future__ import annotations

import numpy as np

from ..hot_kernel import hot_inline, hot_kernel
from .bricks import BRICK, BRICK_SHIFT
from .carve_hooks import (
    BRICK_CARVE,
    BRICK_FAR,
    SphereCarve,
    brick_reach,
    brick_side,
    carve_frame,
    row_span,
    slab_reach,
    voxel_coverage,
)
from .voxels import cache_origin, spacing_and_point

# Layout of the float64 contact vector the carving kernel fills (length N_TOUCH).
TOUCH_FORBIDDEN = 0  # forbidden voxels holding bone that the burr overlaps
TOUCH_VISITED = 1  # voxels examined (cost statistics)
TOUCH_BRICKS = 2  # bricks whose bone changed
TOUCH_NEAR_BONE = 3  # 1 if any brick holding bone lies within the burr's reach
N_TOUCH = 4


@hot_kernel
def carve_voxels(cutter, density, swept, labels, forbidden, brick_bone, brick_full,
                 brick_version, brick_forbidden, spacing, centre, carve, version_next, removed,
                 touch, touched, cache, tick):
    """Sweep the voxels a burr covers (one call per tick).

    Raises each covered voxel's ``swept`` to its coverage (never lowers it; air, density 0,
    straight to 255: the force reads of air only whether a burr reached it), adds the bone
    this removed to ``removed[label]`` (units: density × swept steps, i.e. 255² per voxel
    volume), keeps the brick counts exact and stamps changed bricks with ``version_next``.
    With ``carve`` False nothing is written: the call only reports contact (a burr that is not
    spinning fast enough touches but does not cut).

    Args:
        cutter: the burr (``carve_hooks.SphereCarve`` or ``carve_hooks.RevolvedCarve``).
        density, swept, labels: uint8 voxel arrays (nx, ny, nz).
        forbidden: uint8 (256,), 1 for labels whose contact is recorded.
        brick_bone, brick_full: int32 brick counts; brick_version: int64 per brick.
        brick_forbidden: uint8 per brick, 1 where a forbidden label holds bone.
        spacing: (3,) voxel size, mm.  centre: (3,) the burr's (reference) centre, grid
            frame, mm.
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
    hx, hy, hz, cx, cy, cz = spacing_and_point(spacing, centre)
    i_lo, i_hi, j_lo, j_hi, k_lo, k_hi, frame = carve_frame(cutter, density.shape, hx, hy, hz,
                                                            cx, cy, cz, carve)
    any_removed = False
    visited = 0
    o0, o1, o2 = cache_origin(cache, cx, cy, cz, hx, hy, hz)
    for bi in range(i_lo >> BRICK_SHIFT, (i_hi >> BRICK_SHIFT) + 1):
        a0 = max(bi * BRICK, i_lo)
        a1 = min(bi * BRICK + BRICK - 1, i_hi)
        ex, fx = brick_side(cutter, cx, a0 * hx, a1 * hx)
        for bj in range(j_lo >> BRICK_SHIFT, (j_hi >> BRICK_SHIFT) + 1):
            b0 = max(bj * BRICK, j_lo)
            b1 = min(bj * BRICK + BRICK - 1, j_hi)
            ey, fy = brick_side(cutter, cy, b0 * hy, b1 * hy)
            for bk in range(k_lo >> BRICK_SHIFT, (k_hi >> BRICK_SHIFT) + 1):
                if brick_bone[bi, bj, bk] == 0:
                    continue
                c0 = max(bk * BRICK, k_lo)
                c1 = min(bk * BRICK + BRICK - 1, k_hi)
                reach, brick = brick_reach(cutter, frame, ex, ey, fx, fy, a0, a1, b0, b1, c0,
                                           c1, hx, hy, hz, cx, cy, cz,
                                           brick_forbidden[bi, bj, bk])
                if reach == BRICK_FAR:
                    continue
                touch[TOUCH_NEAR_BONE] = 1.0
                if reach != BRICK_CARVE:
                    continue
                brick_changed = False
                for i in range(a0, a1 + 1):
                    keep, dx = slab_reach(cutter, frame, brick, i, b0, b1, c0, c1, ey, hx, hy,
                                          hz, cx)
                    if not keep:
                        continue
                    for j in range(b0, b1 + 1):
                        dy = j * hy - cy
                        k_first, k_last = row_span(cutter, frame, brick, i, j, dx, dy, c0, c1,
                                                   k_lo, k_hi, o0, o1, tick, hx, hy, hz, cz)
                        if k_first > k_last:
                            # Skipped before the range loop's set-up: most rows of the
                            # sphere's bricks are (measured: 17 k instructions a tick).
                            continue
                        for k in range(k_first, k_last + 1):
                            # Unsigned: numba then omits the negative-index wraparound, 3 of the
                            # 12 instructions a swept-through voxel costs (thousands a tick).
                            old = swept[i, j, np.uint64(k)]
                            if old == 255:
                                continue  # swept through: nothing left to take or touch
                            visited += 1
                            cq = voxel_coverage(cutter, frame, brick, cache, o0, o1, o2, tick,
                                                i, j, k, dx, dy, k * hz - cz, hx, hy, hz)
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


@hot_kernel
def carve_sphere(density, swept, labels, forbidden, brick_bone, brick_full, brick_version,
                 brick_forbidden, spacing, centre, previous, radius, carve, version_next,
                 removed, touch, touched, cache, tick):
    """``carve_voxels`` for a round burr of ``radius`` mm centred at ``centre``.
    ``previous``: (3,) where the same burr last carved, or NaN. A voxel no farther from there
    than from ``centre`` cannot gain coverage, so it is skipped (a burr at rest carves
    nothing); bricks holding forbidden labels are always checked for contact."""
    return carve_voxels(SphereCarve(radius, previous), density, swept, labels, forbidden,
                        brick_bone, brick_full, brick_version, brick_forbidden, spacing, centre,
                        carve, version_next, removed, touch, touched, cache, tick)


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
