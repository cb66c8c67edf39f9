"""Raw voxel values → a :class:`~..bone.Bone`: CT through HU bands, label maps through a
materials file, densities as they are."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from ..bone import Bone
from ..grid import BoneGrid
from ..hounsfield import ct_to_bone
from ..material_map import MaterialMap
from ..materials import BUILTIN_MATERIALS, MaterialTable
from .errors import BoneFileError
from .geometry import make_right_handed
from .volume import KINDS, MAX_LOAD_VOXELS, Progress, RawVolume

#: An integer volume in 0..255 with at most this many distinct values is taken as a label map
#: when its kind is "auto"; with more, as a density.
MAX_AUTO_LABELS = 64
#: Label values must span less than this (the histogram is that long).
MAX_LABEL_SPAN = 1 << 24


@dataclass(frozen=True)
class LoadOptions:
    """How to read a bone file.

    Attributes:
        kind: what the values are: "auto", "ct" (HU), "labels" or "density".
        spacing_mm: voxel size for formats without one (npy, PNG stacks), mm; for others it
            overrides the file's (and says so in the notes).
        origin_mm: position of the first voxel's centre, for formats without one, mm.
        materials: labels/segments/colours → materials, and the CT bands.
        material: the material of a density volume that has no labels.
        series_uid: which DICOM series, when a folder holds several.
        max_voxels: refuse larger volumes.
    """

    kind: str = "auto"
    spacing_mm: tuple[float, float, float] | None = None
    origin_mm: tuple[float, float, float] | None = None
    materials: MaterialMap = field(default_factory=MaterialMap)
    material: str = "cortical"
    series_uid: str | None = None
    max_voxels: int = MAX_LOAD_VOXELS

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {self.kind!r}")


def check_size(path, shape: tuple[int, ...], options: LoadOptions) -> None:
    """Refuse a volume before reading its voxels: wrong dimensionality or too many voxels."""
    if len(shape) != 3:
        raise BoneFileError(path, f"a bone volume is 3-D; this one has shape {tuple(shape)}")
    if min(shape) < 1:
        raise BoneFileError(path, f"the volume is empty: shape {tuple(shape)}")
    n = int(np.prod(np.asarray(shape, dtype=np.int64)))
    if n > options.max_voxels:
        raise BoneFileError(path, f"{tuple(shape)} is {n:,} voxels, more than the "
                                  f"{options.max_voxels:,} allowed: crop or downsample it")


def to_bone(raw: RawVolume, options: LoadOptions, progress: Progress | None = None) -> Bone:
    """Turn ``raw`` into a bone. BoneFileError names the file and what is wrong."""
    path = raw.path
    check_size(path, raw.data.shape, options)
    if raw.labels is not None and raw.labels.shape != raw.data.shape:
        raise BoneFileError(path, f"labels {raw.labels.shape} and density {raw.data.shape} "
                                  "differ in shape")
    notes = list(raw.notes)
    spacing = np.asarray(raw.spacing_mm, dtype=np.float64)
    origin = np.asarray(raw.origin_mm, dtype=np.float64)
    if options.spacing_mm is not None:
        spacing = np.broadcast_to(np.asarray(options.spacing_mm, dtype=np.float64), (3,))
        notes.append(f"spacing {spacing.tolist()} mm given by the user")
    if options.origin_mm is not None:
        origin = np.asarray(options.origin_mm, dtype=np.float64)
        notes.append(f"origin {origin.tolist()} mm given by the user")
    data, origin2, direction = make_right_handed(raw.data, origin, spacing, raw.direction)
    labels_in = raw.labels
    if data is not raw.data:
        if labels_in is not None:
            labels_in = np.flip(labels_in, axis=0)
        notes.append("the file's grid is left-handed: its first axis was flipped (the voxels "
                     "keep their positions)")
    # The kernels walk the voxels as one flat run, and the grid keeps C order: copy a
    # Fortran-ordered (NRRD, NIfTI) or flipped source once here, before it becomes bytes.
    data = _native(data)
    if labels_in is not None:
        labels_in = _native(labels_in)
    stats = _Stats(data)
    kind = raw.kind if options.kind == "auto" else options.kind
    if kind == "auto":
        kind, why = _detect_kind(data, stats)
        notes.append(f"read as {kind}: {why} (override with kind)")
    def report(done: int, total: int) -> None:
        if progress is not None:
            progress("converting", done, total)

    try:
        if kind == "ct":
            if data.dtype == np.bool_ or not np.issubdtype(data.dtype, np.number):
                raise ValueError(f"CT values must be numbers, got {data.dtype}")
            band_labels, table = options.materials.ct_table()
            density, labels = ct_to_bone(data, options.materials.ct, np.array(band_labels),
                                         report)
        elif kind == "labels":
            density, labels, table = _labels_to_bone(data, stats, raw, options)
        else:
            density = _density(data, stats)
            if labels_in is not None:
                _, labels, table = _labels_to_bone(labels_in, _Stats(labels_in), raw, options)
                unlabelled = int(np.count_nonzero((density > 0) & (labels == 0)))
                if unlabelled:
                    raise ValueError(f"{unlabelled:,} voxels hold bone but have label 0 (empty "
                                     "space): give every bone voxel a label")
                labels = np.where(density > 0, labels, np.uint8(0))
            else:
                table, labels = _single_material(density, options)
            report(1, 1)
        grid = BoneGrid(density, spacing, origin_mm=origin2, direction=direction,
                        labels=labels)
    except BoneFileError:
        raise
    except ValueError as exc:
        raise BoneFileError(path, str(exc)) from None
    return Bone(grid, table, name=str(path), format=raw.format, kind=kind, notes=notes)


def _native(array: np.ndarray) -> np.ndarray:
    """C-ordered, native byte order, and no float16 (the kernels read any of the rest)."""
    if array.dtype == np.float16:
        array = array.astype(np.float32)
    elif not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    return np.ascontiguousarray(array)


class _Stats:
    """A volume's value range and histogram, each computed once, when first asked for."""

    def __init__(self, data: np.ndarray) -> None:
        self.data = data
        self._summary: tuple[float, float, bool, bool] | None = None
        self._counts: np.ndarray | None = None

    def scan(self) -> tuple[float, float, bool, bool]:
        """(min, max, all integers, all finite) over the finite values."""
        if self._summary is None:
            data = self.data
            if data.dtype == np.bool_:
                data = data.view(np.uint8)
            if np.issubdtype(data.dtype, np.integer):  # NumPy's min/max are vectorized
                self._summary = (float(data.min()), float(data.max()), True, True)
            else:
                self._summary = _scan(data.reshape(-1))
        return self._summary

    def summary(self) -> tuple[float, float, bool]:
        """(min, max, all integers); ValueError for NaN or ±Inf."""
        lo, hi, integral, finite = self.scan()
        if not finite:
            raise ValueError("the volume holds NaN or infinite values")
        return lo, hi, integral

    def counts(self) -> np.ndarray:
        """Voxels per integer value from min to max (int64)."""
        if self._counts is None:
            lo, hi, _ = self.summary()
            data = self.data.view(np.uint8) if self.data.dtype == np.bool_ else self.data
            self._counts = _histogram(data.reshape(-1), int(lo), int(hi) - int(lo) + 1)
        return self._counts


def _detect_kind(data: np.ndarray, stats: _Stats) -> tuple[str, str]:
    if data.dtype == np.bool_:
        return "density", "a boolean mask"
    if not np.issubdtype(data.dtype, np.number):
        return "density", f"{data.dtype} values"
    lo, hi, integral, finite = stats.scan()
    if not finite:
        return "ct", "non-finite values (NaN or Inf are read as not bone)"
    if not integral:
        if lo >= 0.0 and hi <= 1.0:
            return "density", "fractional values within [0, 1]"
        return "ct", f"values {lo:g}..{hi:g} are not fractions or labels"
    if lo < 0.0 or hi > 255.0:
        return "ct", f"integer values {lo:g}..{hi:g} (HU)"
    counts = stats.counts()
    distinct = int(np.count_nonzero(counts))
    if lo == 0.0 and hi == 255.0 and np.count_nonzero(counts[1:-1]) == 0:
        return "density", "a 0/255 mask"
    if distinct <= MAX_AUTO_LABELS:
        return "labels", f"{distinct} distinct integer values in 0..255"
    return "density", f"{distinct} distinct values in 0..255"


def _density(data: np.ndarray, stats: _Stats) -> np.ndarray:
    if data.dtype == np.uint8:
        return data
    if data.dtype == np.bool_:
        return np.where(data, np.uint8(255), np.uint8(0))
    if not np.issubdtype(data.dtype, np.number):
        raise ValueError(f"density values must be numbers, got {data.dtype}")
    lo, hi, integral = stats.summary()
    if np.issubdtype(data.dtype, np.floating) and lo >= 0.0 and hi <= 1.0:
        return np.rint(data * 255.0).astype(np.uint8)
    if integral and lo >= 0.0 and hi <= 255.0:
        return data.astype(np.uint8)
    raise ValueError(f"density values must be fractions in [0, 1] or integers 0–255, got "
                     f"{lo:g}..{hi:g}{'' if integral else ' (not integers)'}")


def _single_material(density: np.ndarray, options: LoadOptions) -> tuple[MaterialTable,
                                                                           np.ndarray]:
    name = options.material
    try:
        material = options.materials.material(name)
    except KeyError:
        material = BUILTIN_MATERIALS.get(name)
        if material is None:
            raise ValueError(f"material {name!r} is neither in the materials file nor built "
                             f"in ({', '.join(BUILTIN_MATERIALS)})") from None
    labels = np.where(density > 0, np.uint8(1), np.uint8(0))
    return MaterialTable({1: material}), labels


def _labels_to_bone(values: np.ndarray, stats: _Stats, raw: RawVolume, options: LoadOptions):
    if values.dtype == np.bool_:
        values = values.view(np.uint8)
    if not np.issubdtype(values.dtype, np.number):
        raise ValueError(f"label values must be integers, got {values.dtype}")
    lo, hi, integral = stats.summary()
    if not integral:
        raise ValueError("a label map must hold integers (found fractional or non-finite "
                         "values); read it with kind 'ct' or 'density' instead")
    span = int(hi) - int(lo) + 1
    if span > MAX_LABEL_SPAN:
        raise ValueError(f"label values span {lo:g}..{hi:g}, too wide for a label map")
    counts = stats.counts()
    present = [int(lo) + i for i in np.flatnonzero(counts).tolist() if int(lo) + i != 0]
    label_of, table = options.materials.assign(present, raw.segments,
                                               match_values=not raw.numbered_by_reader)
    lut = np.zeros(span, dtype=np.uint8)
    for value, label in label_of.items():
        lut[value - int(lo)] = label
    density = np.empty(values.shape, dtype=np.uint8)
    labels = np.empty(values.shape, dtype=np.uint8)
    _apply_lut(values.reshape(-1), int(lo), lut, density.reshape(-1), labels.reshape(-1))
    return density, labels, table


@njit(cache=True, nogil=True)
def _scan(values):
    """(min, max, all integers, all finite) of a flat float array, over its finite values."""
    lo = np.inf
    hi = -np.inf
    integral = True
    finite = True
    for n in range(values.shape[0]):
        x = float(values[n])
        if not np.isfinite(x):
            finite = False
            continue
        if x < lo:
            lo = x
        if x > hi:
            hi = x
        if integral and x != np.floor(x):
            integral = False
    return lo, hi, integral, finite


@njit(cache=True, nogil=True)
def _histogram(values, lo, span):
    counts = np.zeros(span, dtype=np.int64)
    for n in range(values.shape[0]):
        counts[int(values[n]) - lo] += 1
    return counts


@njit(cache=True, nogil=True)
def _apply_lut(values, lo, lut, density, labels):
    """Flat arrays: each value's label from ``lut``; density 255 where it has one."""
    for n in range(values.shape[0]):
        label = lut[int(values[n]) - lo]
        labels[n] = label
        density[n] = 255 if label != 0 else 0
