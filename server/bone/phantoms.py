"""Bones generated in code. The thesis's workpiece: a block of synthetic cortical bone."""

from __future__ import annotations

import numpy as np
from numba import njit

from .grid import BoneGrid, rotation
from .materials import CORTICAL_LABEL
from .voxels import plane_fraction

#: The workpiece block: x ∈ [0, 26] mm (a 20 mm groove plus a burr's width either side),
#: y ∈ [−8, 8] mm, z ∈ [−8, 0] mm, flat top at z = 0 as in model.md.
WORKPIECE_LO_MM = (0.0, -8.0, -8.0)
WORKPIECE_HI_MM = (26.0, 8.0, 0.0)
#: Air around the block, so a burr can enter through a side face.
WORKPIECE_MARGIN_MM = 3.0
MAX_PHANTOM_VOXELS = 400_000_000


def workpiece_block(
    voxel_mm: float = 0.1,
    lo_mm: tuple[float, float, float] = WORKPIECE_LO_MM,
    hi_mm: tuple[float, float, float] = WORKPIECE_HI_MM,
    margin_mm: float = WORKPIECE_MARGIN_MM,
    offset_voxels: tuple[float, float, float] = (0.0, 0.0, 0.0),
    direction: np.ndarray | None = None,
    label: int = CORTICAL_LABEL,
) -> BoneGrid:
    """The thesis's workpiece: a block of cortical bone (label 1) with partial volume at its
    faces, in a grid of isotropic voxels.

    Args:
        voxel_mm: voxel size, mm.
        lo_mm, hi_mm: the block's corners in the world, mm (default 26 × 16 × 8 mm, top face
            at z = 0).
        margin_mm: air around the block, mm.
        offset_voxels: shifts the grid by a fraction of a voxel along each of its axes, so the
            faces fall inside voxels instead of on voxel boundaries.
        direction: (3, 3) rotation of the grid's axes in the world (default aligned with the
            block). An oblique grid makes every face cut voxels at an angle, as in a scan.

    Partial volume: exact for faces aligned with the grid; for oblique faces each face's
    coverage is ``voxels.plane_fraction`` (as in carving), and the faces' coverages multiply
    (exact away from edges).
    """
    lo = np.asarray(lo_mm, dtype=np.float64)
    hi = np.asarray(hi_mm, dtype=np.float64)
    offset = np.asarray(offset_voxels, dtype=np.float64)
    if lo.shape != (3,) or hi.shape != (3,) or not (hi > lo).all():
        raise ValueError(f"the block needs lo < hi on every axis, got {lo_mm} and {hi_mm}")
    if not (np.abs(np.concatenate([lo, hi])) <= 1e4).all():
        raise ValueError(f"the block's corners must be finite and within ±1e4 mm, got {lo_mm} "
                         f"and {hi_mm}")
    if isinstance(label, bool) or not isinstance(label, (int, np.integer)) \
            or not 1 <= label <= 255:
        raise ValueError(f"label must be a material label in 1..255, got {label!r}")
    if not 0.0 <= margin_mm <= 100.0:
        raise ValueError(f"margin_mm must be in [0, 100], got {margin_mm}")
    if offset.shape != (3,) or not (np.abs(offset) <= 1.0).all():
        raise ValueError(f"offset_voxels must be 3 numbers in [−1, 1], got {offset_voxels}")
    h = float(voxel_mm)
    if not 1e-3 <= h <= 10.0:
        raise ValueError(f"voxel_mm must be in [0.001, 10], got {voxel_mm}")
    rot = rotation(direction)  # validated before the kernel sees it
    # The grid covers the block's bounding box in its own axes, plus the margin.
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    local = corners @ rot  # world → grid axes (rot's columns are the grid axes)
    g_lo = local.min(axis=0) - margin_mm
    g_hi = local.max(axis=0) + margin_mm
    shape = tuple(int(n) for n in np.ceil((g_hi - g_lo) / h))
    if int(np.prod(shape)) > MAX_PHANTOM_VOXELS:
        raise ValueError(f"a {shape} phantom is too large; use coarser voxels")
    origin_grid = g_lo + (0.5 + offset) * h
    origin = rot @ origin_grid
    density = np.empty(shape, dtype=np.uint8)
    _fill_block(density, origin_grid, h, rot, lo, hi)
    labels = np.where(density > 0, np.uint8(label), np.uint8(0)).astype(np.uint8)
    return BoneGrid(density, h, origin_mm=origin, direction=rot, labels=labels)


@njit(cache=True, nogil=True)
def _fill_block(density, origin_grid, h, rot, lo, hi):
    """Partial-volume density (0–255) of the box [lo, hi] (world mm) in a grid of voxel size h
    whose axes are ``rot``'s columns and whose voxel (0, 0, 0) sits at ``origin_grid`` (grid
    mm): per face ``plane_fraction``, multiplied over the six faces."""
    nx, ny, nz = density.shape
    for i in range(nx):
        gx = origin_grid[0] + h * i
        for j in range(ny):
            gy = origin_grid[1] + h * j
            for k in range(nz):
                gz = origin_grid[2] + h * k
                frac = 1.0
                for axis in range(3):
                    # The world axis in grid coordinates is row ``axis`` of rot.
                    r0 = rot[axis, 0]
                    r1 = rot[axis, 1]
                    r2 = rot[axis, 2]
                    world = r0 * gx + r1 * gy + r2 * gz
                    a = 0.5 * h * abs(r0)
                    b = 0.5 * h * abs(r1)
                    c = 0.5 * h * abs(r2)
                    frac *= plane_fraction(world - lo[axis], a, b, c)
                    frac *= plane_fraction(hi[axis] - world, a, b, c)
                    if frac == 0.0:
                        break
                density[i, j, k] = int(frac * 255.0 + 0.5)
