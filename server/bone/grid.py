"""The bone as voxels: geometry, original density, what the burr has swept, labels, bricks.

Each voxel keeps three bytes:

- ``density``: the bone's original partial-volume occupancy, 0–255 (255 = the voxel is all
  bone). Carving never writes it.
- ``swept``: how much of the voxel the spinning burr has swept so far, 0–255 — the largest
  coverage by any burr position while cutting. Carving only raises it (idempotent, exact).
  Air (``density`` 0) keeps only whether a burr has reached it: 255 from the first coverage
  on, where its brick still held bone (the carve skips bricks without bone); the force reads
  no more of it.
- ``labels``: material label (see :mod:`.materials`).

The bone left in a voxel is ``density·(255 − swept)/255``. Keeping what the bone *was* apart
from what the burr *took* lets the force kernel ask the question the model asks — is there bone
where this element is going? — without seeing the burr's own freshly carved surface (which
would halve every fraction at the cutting front).

Geometry: voxel (i, j, k) has its centre at ``origin_mm + direction @ (i·sx, j·sy, k·sz)``
(NRRD/NIfTI convention: the origin is the first voxel's centre). ``direction`` has the grid
axes as orthonormal columns in the world frame and must be a rotation (det +1).
"""

from __future__ import annotations

import numpy as np

from .bricks import (
    EMPTY,
    FULL,
    MIXED,
    bone_by_label,
    brick_shape,
    count_bricks,
    voxels_per_brick,
)
from .materials import CORTICAL_LABEL, N_LABELS
from .orthonormal import nearest_orthonormal

MIN_SPACING_MM = 1e-3
MAX_SPACING_MM = 100.0
MAX_EXTENT_MM = 1e5
MAX_VOXELS = 2**31 - 1  # int32 voxel counters; ≈ 2 G voxels is far beyond any bone we serve


class BoneGrid:
    """A voxel bone with a brick summary and a monotone version.

    Args:
        density: uint8 array of shape (nx, ny, nz): partial-volume bone occupancy, 0–255.
        spacing_mm: voxel size along the grid axes, mm: a number or 3 numbers.
        origin_mm: world position of voxel (0, 0, 0)'s centre, mm.
        direction: (3, 3) rotation whose columns are the grid's i, j, k axes in the world.
        labels: uint8 array of the same shape, or one label for every voxel (default 1, the
            thesis's cortical bone).
        swept: uint8 array of the same shape (a restored session); default nothing swept.
        bricks: (brick_bone, brick_full), int32 arrays of the brick shape already counted for
            these voxels (``count_bricks``): a shared bone's, counted by the process that
            published it, so the hot loop does not scan the voxels again. Default: counted.

    Raises:
        ValueError: wrong dtype, shape or size; spacing, origin or direction out of range.
    """

    def __init__(
        self,
        density: np.ndarray,
        spacing_mm: float | tuple[float, float, float] | np.ndarray,
        origin_mm: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        direction: np.ndarray | None = None,
        labels: np.ndarray | int = CORTICAL_LABEL,
        swept: np.ndarray | None = None,
        bricks: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> None:
        density = _volume("density", density)
        shape = density.shape
        self.density = density
        if isinstance(labels, (int, np.integer)) and not isinstance(labels, bool):
            if not 0 <= int(labels) < N_LABELS:
                raise ValueError(f"labels must be in 0..{N_LABELS - 1}, got {labels}")
            self.labels = np.full(shape, int(labels), dtype=np.uint8)
        else:
            self.labels = _volume("labels", labels, shape)
        self.swept = (np.zeros(shape, dtype=np.uint8) if swept is None
                      else _volume("swept", swept, shape))
        self.spacing_mm = _spacing(spacing_mm)
        self.origin_mm = _finite3("origin_mm", origin_mm, MAX_EXTENT_MM)
        self.direction = rotation(direction)
        extent = np.asarray(shape) * self.spacing_mm
        if not (extent <= MAX_EXTENT_MM).all():
            raise ValueError(f"grid extent {extent.tolist()} mm exceeds {MAX_EXTENT_MM:g} mm")
        self.identity_direction = bool(np.array_equal(self.direction, np.eye(3)))
        bshape = brick_shape(shape)
        if bricks is None:
            self.brick_bone = np.zeros(bshape, dtype=np.int32)
            self.brick_full = np.zeros_like(self.brick_bone)
            count_bricks(self.density, self.swept, self.brick_bone, self.brick_full)
        else:
            self.brick_bone = _bricks("brick_bone", bricks[0], bshape)
            self.brick_full = _bricks("brick_full", bricks[1], bshape)
        self.brick_voxels = np.zeros(bshape, dtype=np.int32)
        self.brick_version = np.zeros(bshape, dtype=np.int64)
        voxels_per_brick(np.array(shape, dtype=np.int64), self.brick_voxels)
        #: Per brick, a bit per label with bone in it (``bricks.brick_labels``), when the
        #: grid came with one (a shared bone's); None: scan the voxels instead.
        self.brick_labels: np.ndarray | None = None
        #: Monotone bone version: bumped by every tick that removed bone.
        self.version = 0
        #: For a grid in shared memory (``shared.SharedBone``): int64 counters the engine
        #: updates around each carving tick so another process can read the voxels
        #: consistently. None for a private grid.
        self.shared_header: np.ndarray | None = None

    @classmethod
    def from_fraction(cls, fraction: np.ndarray, spacing_mm, **kwargs) -> BoneGrid:
        """A grid from bone fractions in [0, 1] (float array of shape (nx, ny, nz))."""
        fraction = np.asarray(fraction, dtype=np.float64)
        if fraction.ndim != 3:
            raise ValueError(f"fraction must be a 3-D array, got {fraction.ndim} dimensions")
        if not np.isfinite(fraction).all() or fraction.min(initial=0.0) < 0.0 \
                or fraction.max(initial=0.0) > 1.0:
            raise ValueError("fraction must be finite and within [0, 1]")
        density = np.rint(fraction * 255.0).astype(np.uint8)
        return cls(density, spacing_mm, **kwargs)

    # -- geometry ---------------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int, int]:
        return self.density.shape  # type: ignore[return-value]

    @property
    def voxel_volume_mm3(self) -> float:
        return float(np.prod(self.spacing_mm))

    def to_grid_point(self, point_mm: np.ndarray) -> np.ndarray:
        """World point → grid frame (mm along the grid axes from voxel (0, 0, 0)'s centre)."""
        return self.direction.T @ (np.asarray(point_mm, dtype=np.float64) - self.origin_mm)

    def to_grid_vector(self, vector: np.ndarray) -> np.ndarray:
        return self.direction.T @ np.asarray(vector, dtype=np.float64)

    def to_world_vector(self, vector: np.ndarray) -> np.ndarray:
        return self.direction @ np.asarray(vector, dtype=np.float64)

    def to_world_point(self, point_grid_mm: np.ndarray) -> np.ndarray:
        return self.origin_mm + self.direction @ np.asarray(point_grid_mm, dtype=np.float64)

    def voxel_centre_mm(self, index: tuple[int, int, int]) -> np.ndarray:
        """World position of voxel ``index``'s centre."""
        return self.to_world_point(np.asarray(index, dtype=np.float64) * self.spacing_mm)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned box (lo, hi) enclosing every voxel."""
        half = 0.5 * self.spacing_mm
        lo_g = -half
        hi_g = (np.asarray(self.shape) - 0.5) * self.spacing_mm
        corners = np.array([[x, y, z] for x in (lo_g[0], hi_g[0]) for y in (lo_g[1], hi_g[1])
                            for z in (lo_g[2], hi_g[2])])
        world = self.origin_mm + corners @ self.direction.T
        return world.min(axis=0), world.max(axis=0)

    # -- state ------------------------------------------------------------------------------
    def remaining_density(self) -> np.ndarray:
        """The bone left in each voxel, uint8 0–255: density·(255 − swept)/255, rounded."""
        left = self.density.astype(np.uint16) * (255 - self.swept.astype(np.uint16))
        return ((left + 127) // 255).astype(np.uint8)

    def bone_volume_by_label_mm3(self) -> np.ndarray:
        """Bone left per label, mm³, float64 of shape (256,)."""
        out = np.zeros(N_LABELS, dtype=np.float64)
        bone_by_label(self.density, self.swept, self.labels, out)
        return out * (self.voxel_volume_mm3 / (255.0 * 255.0))

    def brick_status(self) -> np.ndarray:
        """Per brick: EMPTY (0), MIXED (1) or FULL (2), uint8 of the brick shape."""
        status = np.full(self.brick_bone.shape, MIXED, dtype=np.uint8)
        status[self.brick_full == self.brick_voxels] = FULL
        status[self.brick_bone == 0] = EMPTY
        return status

    def changed_bricks(self, since_version: int) -> np.ndarray:
        """Brick indices (n, 3) whose bone changed after ``since_version``. Brick (a, b, c)
        covers voxels [8a, 8a + 8) × [8b, 8b + 8) × [8c, 8c + 8), clipped to the grid."""
        return np.argwhere(self.brick_version > since_version)

    def recount(self) -> None:
        """Rebuild the brick summary from the voxels (after writing arrays directly)."""
        count_bricks(self.density, self.swept, self.brick_bone, self.brick_full)

    def __repr__(self) -> str:
        return (f"BoneGrid(shape={self.shape}, spacing_mm={self.spacing_mm.tolist()}, "
                f"origin_mm={self.origin_mm.tolist()}, version={self.version})")


def _volume(name: str, array: object, shape: tuple[int, ...] | None = None) -> np.ndarray:
    if not isinstance(array, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(array).__name__}")
    if array.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8 (0–255), got {array.dtype}; "
                         "use BoneGrid.from_fraction for fractions in [0, 1]")
    if array.ndim != 3:
        raise ValueError(f"{name} must be a 3-D array, got shape {array.shape}")
    if min(array.shape) < 1:
        raise ValueError(f"{name} must not be empty, got shape {array.shape}")
    if array.size > MAX_VOXELS:
        raise ValueError(f"{name} has {array.size} voxels, more than {MAX_VOXELS}")
    if shape is not None and array.shape != shape:
        raise ValueError(f"{name} has shape {array.shape}, the density {shape}")
    return np.ascontiguousarray(array)


def _bricks(name: str, array: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(array, np.ndarray) or array.dtype != np.int32 or array.shape != shape \
            or not array.flags.c_contiguous:
        raise ValueError(f"{name} must be a C-contiguous int32 array of shape {shape}")
    return array


def _spacing(spacing: object) -> np.ndarray:
    arr = np.array(spacing, dtype=np.float64).reshape(-1)
    if arr.shape == (1,):
        arr = np.repeat(arr, 3)
    if arr.shape != (3,):
        raise ValueError(f"spacing_mm must be one number or three, got {arr.tolist()}")
    if not ((arr >= MIN_SPACING_MM) & (arr <= MAX_SPACING_MM)).all():
        raise ValueError(f"spacing_mm must be within [{MIN_SPACING_MM:g}, {MAX_SPACING_MM:g}] "
                         f"mm, got {arr.tolist()}")
    return arr


def _finite3(name: str, value: object, limit: float) -> np.ndarray:
    arr = np.array(value, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not (np.abs(arr) <= limit).all():
        raise ValueError(f"{name} must be 3 finite numbers within ±{limit:g}, got {value!r}")
    return arr


def rotation(direction: object) -> np.ndarray:
    """A validated 3×3 rotation (identity for None); ValueError says what is wrong."""
    if direction is None:
        return np.eye(3)
    arr = np.array(direction, dtype=np.float64)
    if arr.shape != (3, 3) or not np.isfinite(arr).all():
        raise ValueError(f"direction must be a finite 3×3 matrix, got shape {arr.shape}")
    if not np.allclose(arr.T @ arr, np.eye(3), atol=1e-6):
        raise ValueError("direction must have orthonormal columns (a rotation; resample "
                         "sheared or scaled grids first)")
    if np.linalg.det(arr) < 0.0:
        raise ValueError("direction is a reflection (det −1): flip one array axis and its "
                         "direction column to make the grid right-handed")
    # Rounding in a file must not skew forces; a direction already orthonormal is kept bit for
    # bit, so a saved grid reloads exactly (on any BLAS).
    return nearest_orthonormal(arr)


def check_voxel_size(spacing_mm: np.ndarray, radius_mm: float) -> None:
    """The burr must span several voxels for its coverage to be resolved."""
    if float(spacing_mm.max()) > radius_mm:
        raise ValueError(f"voxels of {spacing_mm.max():g} mm are coarser than the burr "
                         f"radius {radius_mm:g} mm: resample the bone finer")

