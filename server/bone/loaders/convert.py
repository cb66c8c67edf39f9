"""Raw voxel values → a :class:`~..bone.Bone`: CT through HU bands, label maps through a
materials file, densities as they are.

The values come a block at a time (``slabs``): the bone's uint8 ``density`` and ``labels`` are
written block by block, so a source is never held whole in another dtype. Where the
conversion depends on all the values (a label map's labels, a density's scale, the kind the
values are), one pass gathers their range and histogram first (``value_stats``) and a second
converts them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from ..bone import Bone
from ..grid import BoneGrid
from ..hounsfield import CTClassifier
from ..material_map import MaterialMap
from ..materials import BUILTIN_MATERIALS, MaterialTable
from .budget import require
from .errors import BoneFileError
from .geometry import right_handed
from .kernels import apply_lut
from .slabs import SLAB_BYTES, Index, VoxelSource, as_source
from .value_stats import MAX_LABEL_SPAN, ValueStats, flat, integer_view
from .volume import KINDS, MAX_LOAD_VOXELS, Progress, RawVolume

#: An integer volume in 0..255 with at most this many distinct values is taken as a label map
#: when its kind is "auto"; with more, as a density.
MAX_AUTO_LABELS = 64


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
        memory_budget_bytes: the most memory the load may take (``budget``); None: the
            bone's bytes plus ``budget.DEFAULT_WORK_BYTES``.
    """

    kind: str = "auto"
    spacing_mm: tuple[float, float, float] | None = None
    origin_mm: tuple[float, float, float] | None = None
    materials: MaterialMap = field(default_factory=MaterialMap)
    material: str = "cortical"
    series_uid: str | None = None
    max_voxels: int = MAX_LOAD_VOXELS
    memory_budget_bytes: int | None = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be one of {', '.join(KINDS)}, got {self.kind!r}")


def check_size(path, shape: tuple[int, ...], options: LoadOptions) -> None:
    """Refuse a volume before reading its voxels: wrong dimensionality, too many voxels, or
    more memory than the load budget (``budget.BoneTooLarge``)."""
    if len(shape) != 3:
        raise BoneFileError(path, f"a bone volume is 3-D; this one has shape {tuple(shape)}")
    if min(shape) < 1:
        raise BoneFileError(path, f"the volume is empty: shape {tuple(shape)}")
    n = int(np.prod(np.asarray(shape, dtype=np.int64)))
    if n > options.max_voxels:
        raise BoneFileError(path, f"{tuple(shape)} is {n:,} voxels, more than the "
                                  f"{options.max_voxels:,} allowed: crop or downsample it")
    require(path, tuple(shape), options.memory_budget_bytes)


def to_bone(raw: RawVolume, options: LoadOptions, progress: Progress | None = None) -> Bone:
    """Turn ``raw`` into a bone. BoneFileError names the file and what is wrong."""
    path = raw.path
    source = as_source(raw.data)
    labels_in = None if raw.labels is None else as_source(raw.labels)
    check_size(path, source.shape, options)
    if labels_in is not None and labels_in.shape != source.shape:
        raise BoneFileError(path, f"labels {labels_in.shape} and density {source.shape} "
                                  "differ in shape")
    held = source.held_bytes + (labels_in.held_bytes if labels_in is not None else 0)
    require(path, source.shape, options.memory_budget_bytes, held, "reading it")
    notes = list(raw.notes)
    spacing = np.asarray(raw.spacing_mm, dtype=np.float64)
    origin = np.asarray(raw.origin_mm, dtype=np.float64)
    if options.spacing_mm is not None:
        spacing = np.broadcast_to(np.asarray(options.spacing_mm, dtype=np.float64), (3,))
        notes.append(f"spacing {spacing.tolist()} mm given by the user")
    if options.origin_mm is not None:
        origin = np.asarray(options.origin_mm, dtype=np.float64)
        notes.append(f"origin {origin.tolist()} mm given by the user")
    origin2, direction, flipped = right_handed(origin, spacing, raw.direction,
                                               source.shape[0])
    if flipped:
        notes.append("the file's grid is left-handed: its first axis was flipped (the voxels "
                     "keep their positions)")

    slices = source.shape[2]
    plane = max(source.size // max(slices, 1), 1)

    def stage(name: str) -> Callable[[int, int], None]:
        def report(done: int, total: int) -> None:
            if progress is not None:  # values done, counted in slices of the last axis
                progress(name, done // plane, slices)
        return report

    kind = raw.kind if options.kind == "auto" else options.kind
    stats = ValueStats(source, counts=kind in ("auto", "labels"), progress=stage("reading"))
    if kind == "auto":
        kind, why = _detect_kind(source.dtype, stats)
        notes.append(f"read as {kind}: {why} (override with kind)")
    out = _Voxels(source.shape, flipped)
    converting = stage("converting")
    try:
        if kind == "ct":
            if source.dtype == np.bool_ or not np.issubdtype(source.dtype, np.number):
                raise ValueError(f"CT values must be numbers, got {source.dtype}")
            band_labels, table = options.materials.ct_table()
            _ct(source, CTClassifier(options.materials.ct, np.array(band_labels)), out,
                converting)
        elif kind == "labels":
            table = _labels(source, stats, raw, options, out, converting)
        else:
            _density(source, stats, out, converting)
            if labels_in is not None:
                table = _labels(labels_in, ValueStats(labels_in, progress=stage("reading")),
                                raw, options, out, converting, labels_only=True)
                unlabelled = out.unlabelled_bone()
                if unlabelled:
                    raise ValueError(f"{unlabelled:,} voxels hold bone but have label 0 (empty "
                                     "space): give every bone voxel a label")
                out.unlabel_empty()
            else:
                table = _single_material(out, options)
        grid = BoneGrid(out.density, spacing, origin_mm=origin2, direction=direction,
                        labels=out.labels)
    except BoneFileError:
        raise
    except ValueError as exc:
        raise BoneFileError(path, str(exc)) from None
    return Bone(grid, table, name=str(path), format=raw.format, kind=kind, notes=notes)


class _Voxels:
    """The bone's ``density`` and ``labels`` as the blocks are converted (C order), with the
    file's first axis flipped when its grid is left-handed."""

    def __init__(self, shape: tuple[int, int, int], flipped: bool) -> None:
        self.density = np.empty(shape, dtype=np.uint8)
        self.labels = np.empty(shape, dtype=np.uint8)
        self.flipped = flipped
        self.n0 = shape[0]

    def put(self, index: Index, density: np.ndarray | None,
            labels: np.ndarray | None = None) -> None:
        """Write a block's voxels at ``index`` (the file's index of the block)."""
        if self.flipped:
            first = index[0]
            index = (slice(self.n0 - first.stop, self.n0 - first.start), index[1], index[2])
            density = None if density is None else density[::-1]
            labels = None if labels is None else labels[::-1]
        if density is not None:
            self.density[index] = density
        if labels is not None:
            self.labels[index] = labels

    def runs(self) -> Iterator[slice]:
        """Slabs along the first axis, for passes over the written voxels."""
        plane = max(int(np.prod(self.density.shape[1:])), 1)
        step = max(SLAB_BYTES // plane, 1)
        for start in range(0, self.n0, step):
            yield slice(start, min(start + step, self.n0))

    def unlabelled_bone(self) -> int:
        """Voxels with bone and label 0."""
        return sum(int(np.count_nonzero((self.density[s] > 0) & (self.labels[s] == 0)))
                   for s in self.runs())

    def unlabel_empty(self) -> None:
        """Label 0 wherever there is no bone."""
        for s in self.runs():
            self.labels[s][self.density[s] == 0] = 0


def _ct(source: VoxelSource, classify: CTClassifier, out: _Voxels,
        progress: Callable[[int, int], None]) -> None:
    done = 0
    for index, block in source.blocks():
        values, order = flat(block)
        density = np.empty(values.size, dtype=np.uint8)
        labels = np.empty(values.size, dtype=np.uint8)
        classify(values.reshape(1, 1, -1), density.reshape(1, 1, -1), labels.reshape(1, 1, -1))
        out.put(index, density.reshape(block.shape, order=order),
                labels.reshape(block.shape, order=order))
        done += values.size
        progress(done, source.size)


def _detect_kind(dtype: np.dtype, stats: ValueStats) -> tuple[str, str]:
    if dtype == np.bool_:
        return "density", "a boolean mask"
    if not np.issubdtype(dtype, np.number):
        return "density", f"{dtype} values"
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


def _density(source: VoxelSource, stats: ValueStats, out: _Voxels,
             progress: Callable[[int, int], None]) -> None:
    """Densities 0–255 from uint8 values as they are, a mask, fractions or integers."""
    dtype = source.dtype
    to_uint8: Callable[[np.ndarray], np.ndarray]
    if dtype == np.uint8:
        def to_uint8(values):
            return values
    elif dtype == np.bool_:
        def to_uint8(values):
            return np.where(values, np.uint8(255), np.uint8(0))
    elif not np.issubdtype(dtype, np.number):
        raise ValueError(f"density values must be numbers, got {dtype}")
    else:
        lo, hi, integral = stats.summary()
        if np.issubdtype(dtype, np.floating) and lo >= 0.0 and hi <= 1.0:
            def to_uint8(values):
                return np.rint(values * 255.0).astype(np.uint8)
        elif integral and lo >= 0.0 and hi <= 255.0:
            def to_uint8(values):
                return values.astype(np.uint8)
        else:
            raise ValueError(f"density values must be fractions in [0, 1] or integers 0–255, "
                             f"got {lo:g}..{hi:g}{'' if integral else ' (not integers)'}")
    done = 0
    for index, block in source.blocks():
        out.put(index, to_uint8(block))
        done += block.size
        progress(done, source.size)


def _single_material(out: _Voxels, options: LoadOptions) -> MaterialTable:
    name = options.material
    try:
        material = options.materials.material(name)
    except KeyError:
        material = BUILTIN_MATERIALS.get(name)
        if material is None:
            raise ValueError(f"material {name!r} is neither in the materials file nor built "
                             f"in ({', '.join(BUILTIN_MATERIALS)})") from None
    for s in out.runs():
        np.greater(out.density[s], 0, out=out.labels[s].view(np.bool_))
    return MaterialTable({1: material})


def _labels(source: VoxelSource, stats: ValueStats, raw: RawVolume, options: LoadOptions,
            out: _Voxels, progress: Callable[[int, int], None],
            labels_only: bool = False) -> MaterialTable:
    """A label map's labels (and, unless ``labels_only``, its density: 255 where labelled)
    through the materials file."""
    dtype = source.dtype
    if dtype != np.bool_ and not np.issubdtype(dtype, np.number):
        raise ValueError(f"label values must be integers, got {dtype}")
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
    done = 0
    for index, block in source.blocks():
        values, order = flat(integer_view(block))
        density = np.empty(values.size, dtype=np.uint8)
        labels = np.empty(values.size, dtype=np.uint8)
        apply_lut(values, int(lo), lut, density, labels)
        out.put(index, None if labels_only else density.reshape(block.shape, order=order),
                labels.reshape(block.shape, order=order))
        done += values.size
        progress(done, source.size)
    return table
