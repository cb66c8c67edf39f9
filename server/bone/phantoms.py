"""Bones generated in code. The thesis's workpiece: a block of synthetic cortical bone."""

from __future__ import annotations

import numpy as np

from .grid import BoneGrid
from .materials import CORTICAL_LABEL

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
    coverage is the trapezoid of the voxel's extent along its normal (as in carving), and the
    faces' coverages multiply (exact away from edges).
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
    rot = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64)
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
    axes = [origin_grid[a] + h * np.arange(shape[a]) for a in range(3)]
    ys, zs = np.meshgrid(axes[1], axes[2], indexing="ij")
    for i, x in enumerate(axes[0]):
        # World coordinates of this slab's voxel centres, (ny, nz, 3).
        pts = (x * rot[:, 0] + ys[..., None] * rot[:, 1] + zs[..., None] * rot[:, 2])
        frac = np.ones(ys.shape)
        for axis in range(3):
            normal_grid = rot[axis]  # the world axis in grid coordinates
            spread = 0.5 * h * np.abs(normal_grid)
            frac *= _face_coverage(pts[..., axis] - lo[axis], spread)
            frac *= _face_coverage(hi[axis] - pts[..., axis], spread)
        density[i] = np.rint(frac * 255.0).astype(np.uint8)
    labels = np.where(density > 0, np.uint8(label), np.uint8(0)).astype(np.uint8)
    return BoneGrid(density, h, origin_mm=origin, direction=rot, labels=labels)


def _face_coverage(depth: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """Share of voxels whose centres lie ``depth`` mm inside a plane, given the voxel's three
    half-extents along its normal (``spread``): the trapezoid of ``sphere_coverage``."""
    largest = float(spread.max())
    big = max(largest, float(spread.sum()) - largest)
    small = float(spread.sum()) - big
    if small <= 1e-12 * big:
        return np.clip(0.5 + 0.5 * depth / big, 0.0, 1.0)
    x = depth / big
    r = small / big
    out = np.where(x <= r - 1.0, (x + 1.0 + r) ** 2 / (8.0 * r), 0.5 + 0.5 * x)
    out = np.where(x >= 1.0 - r, 1.0 - (1.0 + r - x) ** 2 / (8.0 * r), out)
    out = np.where(x <= -(1.0 + r), 0.0, out)
    return np.where(x >= 1.0 + r, 1.0, out)
