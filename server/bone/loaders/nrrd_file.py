"""NRRD volumes (``.nrrd``, ``.nhdr``) with pynrrd, including 3D Slicer ``.seg.nrrd``."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import nrrd
import numpy as np

from ..material_map import Segment
from .budget import require
from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import from_axes, mm_per_unit, to_lps
from .payload import Payload
from .slabs import Block, StreamSource, VoxelSource, as_source
from .volume import Progress, RawVolume

#: NRRD ``space`` values → the patient frame to convert from (None: taken as given).
SPACES = {
    "left-posterior-superior": "LPS", "lps": "LPS",
    "right-anterior-superior": "RAS", "ras": "RAS",
    "left-anterior-superior": "LAS", "las": "LAS",
    "scanner-xyz": None, "3d-right-handed": None,
}
_SEGMENT_KEY = re.compile(r"^Segment(\d+)_ID$")


def read_nrrd(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """A NRRD volume, or a 3D Slicer segmentation (3-D label map or 4-D layers).

    The voxels are not read here: the volume's :class:`~.slabs.StreamSource` reads (and
    inflates) them a block at a time while they are converted; a segmentation's layers are
    combined into one label map a block at a time then too."""
    with open(path, "rb") as fh:
        try:
            header = nrrd.read_header(fh)
        except (nrrd.NRRDError, ValueError, TypeError, UnicodeDecodeError) as exc:
            raise BoneFileError(path, f"not a valid NRRD header: {exc}") from None
        data_start = fh.tell()
    sizes = tuple(int(s) for s in header.get("sizes", ()))
    segments = _segments(path, header, len(sizes) == 4)
    layered = len(sizes) == 4 and bool(segments)
    check_size(path, sizes[1:] if layered else sizes, options)
    if layered and int(np.prod(sizes, dtype=np.int64)) > options.max_voxels:
        raise BoneFileError(path, f"{sizes[0]} layers of {sizes[1:]} voxels are more than "
                                  f"the {options.max_voxels:,} allowed")
    spatial = slice(1, 4) if layered else slice(0, 3)
    spacing, origin, direction, notes = _geometry(path, header, spatial, options)
    # A layered file is read as a volume whose fastest axis holds every layer of a voxel row.
    shape = (sizes[0] * sizes[1], sizes[2], sizes[3]) if layered else sizes
    data = _voxels(path, header, data_start, shape, options)
    if not segments:
        return RawVolume(path, "nrrd", data, spacing, origin, direction, notes=notes)
    values = _Segments(path, data, sizes[0] if layered else 1, segments, options)
    return RawVolume(path, "nrrd", values, spacing, origin, direction, kind="labels",
                     segments={i + 1: s for i, (s, _, _) in enumerate(segments)},
                     numbered_by_reader=True, notes=notes)


def _voxels(path: Path, header: dict, data_start: int, shape: tuple[int, ...],
            options: LoadOptions) -> StreamSource | np.ndarray:
    """The voxel values, Fortran order: a source reading the payload (raw, gzip, bzip2), or
    for ASCII data (small files: text is 3–20 bytes a value) the array pynrrd reads."""
    try:
        dtype = np.dtype(nrrd.reader._determine_datatype(header))
    except (nrrd.NRRDError, KeyError) as exc:
        raise BoneFileError(path, f"not a valid NRRD header: {exc}") from None
    encoding = str(header.get("encoding", "raw")).lower()
    count = int(np.prod(shape, dtype=np.int64))
    if encoding in ("ascii", "text", "txt"):
        require(path, tuple(shape), options.memory_budget_bytes, 2 * count * dtype.itemsize,
                "its text values")
        with open(path, "rb") as fh:
            fh.seek(data_start)
            try:
                data = nrrd.read_data(header, fh, filename=str(path), index_order="F")
            except (nrrd.NRRDError, ValueError, EOFError, OSError) as exc:
                raise BoneFileError(path, f"the voxel data is damaged or truncated: "
                                          f"{exc}") from None
        return data.reshape(shape, order="F")
    codec = {"raw": "raw", "gzip": "gzip", "gz": "gzip", "bzip2": "bzip2",
             "bz2": "bzip2"}.get(encoding)
    if codec is None:
        raise BoneFileError(path, f"unsupported NRRD encoding {header.get('encoding')!r} "
                                  "(known: raw, gzip, bzip2, ascii)")
    file, offset = _data_file(path, header, data_start)
    lines = int(header.get("lineskip", header.get("line skip", 0)))
    skip = int(header.get("byteskip", header.get("byte skip", 0)))
    if lines < 0 or skip < -1 or (skip == -1 and codec != "raw"):
        raise BoneFileError(path, f"line skip {lines} and byte skip {skip} are not supported "
                                  f"with {codec} data")
    payload = Payload(path, file, offset, codec, count * dtype.itemsize, skip, lines)
    payload.check()
    return StreamSource(payload, shape, dtype, fortran=True)


def _data_file(path: Path, header: dict, data_start: int) -> tuple[Path, int]:
    """The file holding the voxels, and where they start in it."""
    data_file = header.get("datafile", header.get("data file"))
    if data_file is None:
        return path, data_start
    if not isinstance(data_file, str) or data_file.startswith("LIST") or \
            ("%" in data_file and len(data_file.split()) >= 4):
        raise BoneFileError(path, "several detached data files are not supported")
    # Beside the header or below it, never elsewhere: a header is often an upload, and a
    # detached file naming /etc/… or ../… would turn any readable file into voxels.
    folder = path.parent.resolve()
    source = (folder / data_file).resolve()
    if not source.is_relative_to(folder):
        raise BoneFileError(path, f"the detached data file {data_file!r} lies outside the "
                                  "header's folder: put it beside the header and name it "
                                  "relative to it")
    return source, 0


def _geometry(path: Path, header: dict, spatial: slice, options: LoadOptions):
    notes: list[str] = []
    if "space directions" in header:
        rows = np.asarray(header["space directions"], dtype=np.float64)[spatial]
        if rows.shape != (3, 3) or not np.isfinite(rows).all():
            raise BoneFileError(path, "space directions must give three spatial axes in 3-D "
                                      f"space, got {rows.tolist()}")
        axes = rows.T
    elif "spacings" in header:
        spacing = np.asarray(header["spacings"], dtype=np.float64)[spatial]
        if spacing.shape != (3,) or not np.isfinite(spacing).all():
            raise BoneFileError(path, f"spacings must give three numbers, got {spacing}")
        axes = np.diag(spacing)
        notes.append("no space directions: axes taken as the world axes")
    elif options.spacing_mm is not None:
        axes = np.diag(np.broadcast_to(np.asarray(options.spacing_mm, dtype=float), (3,)))
    else:
        raise BoneFileError(path, "no voxel size in the header (space directions or "
                                  "spacings): give spacing_mm")
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=np.float64)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise BoneFileError(path, f"space origin must be 3 finite numbers, got {origin}")
    units = header.get("space units")
    if units:
        scales = {mm_per_unit(path, u) for u in units}
        if len(scales) != 1:
            raise BoneFileError(path, f"mixed space units {units}")
        scale = scales.pop()
        axes, origin = axes * scale, origin * scale
        if scale != 1.0:
            notes.append(f"converted from {units[0]} to mm")
    else:
        notes.append("no space units: millimetres assumed")
    spacing, direction = from_axes(path, axes)
    space = str(header.get("space", "")).strip().lower()
    if space and space not in SPACES:
        raise BoneFileError(path, f"unsupported NRRD space {header['space']!r} (known: "
                                  f"{', '.join(k for k in SPACES if len(k) > 3)})")
    frame = SPACES.get(space)
    if frame is not None:
        origin, direction = to_lps(origin, direction, frame)
        if frame != "LPS":
            notes.append(f"converted from {frame} to LPS")
    return spacing, origin, direction, notes


def _segments(path: Path, header: dict, layered: bool) -> list[tuple[Segment, int, int]]:
    """(segment, layer, label value) per 3D Slicer segment, in segment order.

    Missing fields take 3D Slicer's own defaults: a segment's layer is its index (older Slicer
    wrote one layer per segment), its label value 1. Two segments on the same layer with the
    same value would be indistinguishable: an error, not a silent merge."""
    indices = sorted(int(m.group(1)) for k in header if (m := _SEGMENT_KEY.match(k)))
    names = _utf8_fields(path)
    found = []
    seen: dict[tuple[int, int], str] = {}
    for i in indices:
        prefix = f"Segment{i}_"
        name = names.get(prefix + "Name") or str(header.get(prefix + "Name", f"Segment {i}"))
        try:
            layer = int(header.get(prefix + "Layer", i if layered else 0))
            value = int(header.get(prefix + "LabelValue", 1))
            color = None
            if prefix + "Color" in header:
                rgb = [float(c) for c in str(header[prefix + "Color"]).split()]
                if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
                    raise ValueError(f"colour {header[prefix + 'Color']!r}")
                color = tuple(round(c * 255) for c in rgb)
        except ValueError as exc:
            raise BoneFileError(path, f"segment {i} ({name!r}) has a bad field: {exc}") from None
        if (layer, value) in seen:
            raise BoneFileError(path, f"segments {seen[layer, value]!r} and {name!r} are both "
                                      f"value {value} on layer {layer} (a Layer or LabelValue "
                                      "field is missing or wrong)")
        seen[layer, value] = name
        found.append((Segment(name, color), layer, value))
    return found


def _utf8_fields(path: Path) -> dict[str, str]:
    """The header's ``key:=value`` fields decoded as UTF-8 (3D Slicer writes segment names in
    UTF-8; pynrrd reads headers as ASCII and drops what it cannot decode)."""
    fields = {}
    with open(path, "rb") as f:
        for raw in f:
            line = raw.rstrip(b"\r\n")
            if not line:
                break  # the blank line that ends the header
            key, sep, value = line.partition(b":=")
            if sep:
                fields[key.decode("utf-8", "replace")] = value.decode("utf-8", "replace")
    return fields


class _Segments(VoxelSource):
    """One label volume (segment s → value s + 1) from a segmentation's layers, combined a
    block at a time as the converter reads it (the layers are read, and inflated, again for
    each pass). Where segments overlap the later one wins, and forbidden ones win over all: a
    nerve inside a filled bone segment must stay a nerve.

    Args:
        path: the file (errors name it).
        layers: the layers as one volume whose fastest axis holds every layer of a row.
        n_layers: layers in the file (1: a collapsed label map).
        segments: (segment, layer, label value) per segment, in segment order.
        options: the materials file says which segments are forbidden.
    """

    def __init__(self, path: Path, layers: StreamSource | np.ndarray, n_layers: int,
                 segments: list[tuple[Segment, int, int]], options: LoadOptions) -> None:
        for segment, layer, _ in segments:
            if not 0 <= layer < n_layers:
                raise BoneFileError(path, f"segment {segment.name!r} is on layer {layer}, "
                                          f"but there are {n_layers} layers")
        self.layers = as_source(layers)
        self.n_layers = n_layers
        self.nx = self.layers.shape[0] // n_layers
        self.shape = (self.nx, *self.layers.shape[1:])  # type: ignore[assignment]
        self.dtype = np.dtype(np.uint8 if len(segments) < 255 else np.uint16)
        self.held_bytes = self.layers.held_bytes
        self.segments = segments
        self.order = sorted(range(len(segments)),
                            key=lambda s: options.materials.is_forbidden(s + 1, segments[s][0]))

    def blocks(self) -> Iterator[Block]:
        for index, block in self.layers.blocks():
            # A block holds whole rows of the fastest axis: every layer of nx voxels.
            layers = block.reshape((self.n_layers, self.nx, *block.shape[1:]), order="F")
            values = np.zeros(layers.shape[1:], dtype=self.dtype)
            for s in self.order:
                _, layer, value = self.segments[s]
                values[layers[layer] == value] = s + 1
            yield (slice(0, self.nx), index[1], index[2]), values
