"""Voxel geometry from files: units, patient frames, affines, reflections.

burrforce's world frame for loaded bones is the patient frame DICOM and ITK use, LPS (x toward
the patient's left, y posterior, z superior), in millimetres. Files in RAS (NIfTI, older 3D
Slicer NRRD) are converted on load; the conversion is a rotation by 180° about z, so it keeps
the frame right-handed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..orthonormal import nearest_orthonormal
from .errors import BoneFileError

#: Millimetres per unit of length, for the unit strings files carry.
MM_PER_UNIT = {
    "mm": 1.0, "millimeter": 1.0, "millimetre": 1.0, "millimeters": 1.0,
    "m": 1000.0, "meter": 1000.0, "metre": 1000.0, "meters": 1000.0,
    "cm": 10.0, "centimeter": 10.0,
    "um": 1e-3, "µm": 1e-3, "μm": 1e-3, "micron": 1e-3, "microns": 1e-3, "micrometer": 1e-3,
}

#: Sign of each axis when converting a named patient frame to LPS.
TO_LPS = {
    "LPS": (1.0, 1.0, 1.0),
    "RAS": (-1.0, -1.0, 1.0),
    "LAS": (1.0, -1.0, 1.0),
    "RPS": (-1.0, 1.0, 1.0),
}

#: Largest departure from orthogonality accepted between grid axes (cosine); anything more is
#: a sheared grid (a tilted CT gantry) that must be resampled first.
MAX_SHEAR_COS = 1e-3


def mm_per_unit(path: Path, unit: str) -> float:
    """Millimetres per ``unit`` (a length unit string from a file header)."""
    scale = MM_PER_UNIT.get(unit.strip().lower())
    if scale is None:
        raise BoneFileError(path, f"unknown length unit {unit!r} (known: mm, cm, m, um)")
    return scale


def from_axes(path: Path, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split voxel step vectors into spacing and direction.

    Args:
        axes: (3, 3) array whose column c is the world step (mm) from one voxel to the next
            along array axis c.

    Returns:
        ``(spacing_mm (3,), direction (3, 3))``: the columns' lengths and the unit columns. The
        direction may still be a reflection; :func:`right_handed` fixes that.

    Raises:
        BoneFileError: a non-finite, zero-length or sheared axis.
    """
    axes = np.asarray(axes, dtype=np.float64)
    if axes.shape != (3, 3) or not np.isfinite(axes).all():
        raise BoneFileError(path, f"voxel axes must be a finite 3×3 matrix, got {axes.tolist()}")
    spacing = np.linalg.norm(axes, axis=0)
    if not (spacing > 0.0).all():
        raise BoneFileError(path, f"a voxel axis has zero length: spacing {spacing.tolist()}")
    direction = axes / spacing
    gram = direction.T @ direction
    off = np.abs(gram - np.eye(3)).max()
    if off > MAX_SHEAR_COS:
        raise BoneFileError(
            path, f"the grid is sheared (axes {np.degrees(np.arccos(np.clip(1 - off, -1, 1))):.2f}"
                  "° from orthogonal, as from a tilted CT gantry): resample it onto a "
                  "rectilinear grid first")
    # Files store directions to a few decimals: snap to the nearest orthonormal matrix (the
    # polar factor keeps the determinant's sign), so a rounded rotation is still a rotation.
    # One stored in full is kept as it is, so a written grid reads back the same.
    return spacing, nearest_orthonormal(direction)


def right_handed(
    origin_mm: np.ndarray, spacing_mm: np.ndarray, direction: np.ndarray, n0: int,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The geometry of a grid whose first axis (``n0`` voxels) is flipped when it is
    left-handed, keeping every voxel where it is.

    Radiological NIfTI and many DICOM stacks store a reflection (det −1); BoneGrid wants a
    rotation.

    Returns:
        ``(origin_mm, direction, flipped)``: unchanged and False when already right-handed;
        else the flipped grid's, and True: voxel i of the file is voxel n0 − 1 − i of the
        grid.
    """
    if np.linalg.det(direction) > 0.0:
        return origin_mm, direction, False
    origin = origin_mm + direction[:, 0] * spacing_mm[0] * (n0 - 1)
    flipped = direction.copy()
    flipped[:, 0] = -flipped[:, 0]
    return origin, flipped, True


def to_lps(origin: np.ndarray, direction: np.ndarray, frame: str) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """Origin (3,) and direction (3, 3) given in patient ``frame`` (LPS, RAS, …) → LPS."""
    sign = np.asarray(TO_LPS[frame])
    return origin * sign + 0.0, direction * sign[:, None] + 0.0  # + 0.0: no −0 in reports
