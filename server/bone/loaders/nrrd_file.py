"""NRRD volumes (``.nrrd``, ``.nhdr``) with pynrrd, including 3D Slicer ``.seg.nrrd``."""

from __future__ import annotations

import bz2
import re
import zlib
from pathlib import Path
from typing import BinaryIO

import nrrd
import numpy as np

from ..material_map import Segment
from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import from_axes, mm_per_unit, to_lps
from .volume import Progress, RawVolume

#: NRRD ``space`` values → the patient frame to convert from (None: taken as given).
SPACES = {
    "left-posterior-superior": "LPS", "lps": "LPS",
    "right-anterior-superior": "RAS", "ras": "RAS",
    "left-anterior-superior": "LAS", "las": "LAS",
    "scanner-xyz": None, "3d-right-handed": None,
}
_SEGMENT_KEY = re.compile(r"^Segment(\d+)_ID$")
_CHUNK = 1 << 20


def read_nrrd(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """A NRRD volume, or a 3D Slicer segmentation (3-D label map or 4-D layers)."""
    with open(path, "rb") as fh:
        try:
            header = nrrd.read_header(fh)
        except (nrrd.NRRDError, ValueError, TypeError, UnicodeDecodeError) as exc:
            raise BoneFileError(path, f"not a valid NRRD header: {exc}") from None
        sizes = tuple(int(s) for s in header.get("sizes", ()))
        segments = _segments(path, header, len(sizes) == 4)
        layered = len(sizes) == 4 and bool(segments)
        check_size(path, sizes[1:] if layered else sizes, options)
        if layered and int(np.prod(sizes, dtype=np.int64)) > options.max_voxels:
            raise BoneFileError(path, f"{sizes[0]} layers of {sizes[1:]} voxels are more than "
                                      f"the {options.max_voxels:,} allowed")
        if progress is not None:
            progress("reading", 0, 1)
        _check_expansion(path, header, fh, int(np.prod(sizes, dtype=np.int64)))
        try:
            data = nrrd.read_data(header, fh, filename=str(path), index_order="F")
        except (nrrd.NRRDError, ValueError, EOFError, zlib.error, OSError) as exc:
            raise BoneFileError(path, f"the voxel data is damaged or truncated: "
                                      f"{exc}") from None
    if progress is not None:
        progress("reading", 1, 1)
    if tuple(data.shape) != sizes:
        raise BoneFileError(path, f"the data has shape {data.shape}, the header says {sizes}")
    spatial = slice(1, 4) if layered else slice(0, 3)
    spacing, origin, direction, notes = _geometry(path, header, spatial, options)
    if not segments:
        return RawVolume(path, "nrrd", data, spacing, origin, direction, notes=notes)
    values = _combine_segments(path, data if layered else data[None], segments, options)
    return RawVolume(path, "nrrd", values, spacing, origin, direction, kind="labels",
                     segments={i + 1: s for i, (s, _, _) in enumerate(segments)},
                     numbered_by_reader=True, notes=notes)


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


def _check_expansion(path: Path, header: dict, fh: BinaryIO, count: int) -> None:
    """Refuse compressed data that inflates past what the header declares, before pynrrd
    inflates all of it (a few kB of bzip2 can claim gigabytes)."""
    encoding = str(header.get("encoding", "raw")).lower()
    if encoding not in ("gzip", "gz", "bzip2", "bz2"):
        return
    itemsize = np.dtype(nrrd.reader._determine_datatype(header)).itemsize
    skip = int(header.get("byteskip", header.get("byte skip", 0)))
    limit = max(skip, 0) + count * itemsize if skip >= 0 else 2 * count * itemsize
    data_file = header.get("datafile", header.get("data file"))
    start = fh.tell()
    if data_file is not None:
        if not isinstance(data_file, str):
            raise BoneFileError(path, "several detached data files are not supported")
        source = Path(data_file) if Path(data_file).is_absolute() else path.parent / data_file
        stream: BinaryIO = open(source, "rb")  # closed in finally
    else:
        stream = fh
    try:
        for _ in range(int(header.get("lineskip", header.get("line skip", 0)))):
            stream.readline()
        inflater = (zlib.decompressobj(zlib.MAX_WBITS | 16) if encoding.startswith("g")
                    else bz2.BZ2Decompressor())
        total = 0
        while (chunk := stream.read(_CHUNK)) and not getattr(inflater, "eof", False):
            while True:  # inflate this chunk, never more than limit + 1 bytes in all
                total += len(inflater.decompress(chunk, limit + 1 - total))
                if total > limit:
                    raise BoneFileError(path, f"the compressed data inflates past the "
                                              f"{limit:,} bytes its header declares")
                chunk = _pending(inflater)
                if chunk is None:
                    break
    except BoneFileError:
        raise
    except (zlib.error, OSError, EOFError, ValueError) as exc:
        raise BoneFileError(path, f"the voxel data is damaged or truncated: {exc}") from None
    finally:
        if stream is not fh:
            stream.close()
        fh.seek(start)


def _pending(inflater) -> bytes | None:
    """What to feed the inflater next for the current chunk, or None when it is done with it:
    zlib keeps back input (unconsumed_tail), bz2 keeps back output (fed with b"")."""
    if isinstance(inflater, bz2.BZ2Decompressor):
        return None if inflater.needs_input or inflater.eof else b""
    return inflater.unconsumed_tail or None


def _combine_segments(
    path: Path, layers: np.ndarray, segments: list[tuple[Segment, int, int]], options: LoadOptions,
) -> np.ndarray:
    """One label volume (segment s → value s + 1) from the layers. Where segments overlap
    the later one wins, and forbidden ones win over all: a nerve inside a filled bone segment
    must stay a nerve."""
    n_layers = layers.shape[0]
    dtype = np.uint8 if len(segments) < 255 else np.uint16
    values = np.zeros(layers.shape[1:], dtype=dtype)
    order = sorted(range(len(segments)),
                   key=lambda s: options.materials.is_forbidden(s + 1, segments[s][0]))
    for s in order:
        segment, layer, value = segments[s]
        if not 0 <= layer < n_layers:
            raise BoneFileError(path, f"segment {segment.name!r} is on layer {layer}, but "
                                      f"there are {n_layers} layers")
        values[layers[layer] == value] = s + 1
    return values
