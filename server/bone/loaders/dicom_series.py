"""DICOM series with pydicom: a folder of single-frame slices, or one file of such a series.

Two passes. The first reads headers only (no pixel data), picks the series, and checks that its
slices make one rectilinear grid: same size, pixel spacing and orientation, positions along the
slice normal with a uniform step and no sideways drift. Only then, and after the size check,
does the second pass decode the pixels and rescale them to HU, one slice at a time as the
converter reaches it (``slabs.SliceSource``: the series is never held whole as HU). Slices
are ordered by where they
are (ImagePositionPatient projected on the slice normal), never by file name or InstanceNumber,
which scanners and anonymisers number in either direction.

DICOM's patient frame is LPS millimetres, which is our world frame, so positions and
orientations are used as they are.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
from pydicom.errors import InvalidDicomError
from pydicom.multival import MultiValue
from pydicom.uid import UID, DeflatedExplicitVRLittleEndian, MediaStorageDirectoryStorage

from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import MAX_SHEAR_COS, from_axes
from .slabs import SliceSource
from .volume import Progress, RawVolume

#: Largest difference between slices' PixelSpacing (mm) or ImageOrientationPatient (direction
#: cosines) still taken as the same: DS values are decimal strings, often rounded to 6 digits.
SAME_GEOMETRY_TOL = 1e-4
#: ImageOrientationPatient vectors must be unit length within this (they are renormalised).
UNIT_VECTOR_TOL = 1e-3
#: A gap between neighbouring slices may differ from the median step by this fraction of it...
STEP_REL_TOL = 0.01
#: ...or by this much, mm, whichever is larger (positions are rounded decimal strings), but the
#: absolute allowance never exceeds STEP_ABS_TOL_MAX_FRACTION of the step, so a missing slice
#: is still caught in micro-CT with steps of a few µm.
STEP_ABS_TOL_MM = 0.01
STEP_ABS_TOL_MAX_FRACTION = 0.25
#: Slices closer than this along the normal are at the same position, mm.
SAME_POSITION_MM = 1e-3
#: Slice origins may stray this far, mm, from the line through the first one along the normal,
#: plus MAX_SHEAR_COS per mm along it (the shear from_axes accepts between grid axes).
LATERAL_TOL_MM = 0.01
#: int16 holds HU when slopes and intercepts are integers and the values fit.
INT16_MIN, INT16_MAX = -32768, 32767
#: The first bytes of the Pixel Data group (7FE0) in little and big endian files.
_PIXEL_GROUP = (b"\xe0\x7f", b"\x7f\xe0")


@dataclass
class _Slice:
    """What the header pass learns about one image file.

    ``problem`` is set for a file that belongs to a series but cannot be used (truncated, bad
    values); it is reported only when that series is the one being loaded.
    """

    path: Path
    forced: bool  # read with force=True: a .dcm file without the DICOM preamble
    series_uid: str
    modality: str = ""
    description: str = ""
    series_number: int | None = None
    transfer_syntax: str = ""
    problem: str | None = None
    frames: int = 1
    enhanced: bool = False
    rows: int = 0
    cols: int = 0
    pixel_spacing_mm: np.ndarray | None = None  # (2,) [between rows, between columns]
    orientation: np.ndarray | None = None  # (6,) row direction then column direction
    position_mm: np.ndarray | None = None  # (3,) centre of the first pixel
    slope: float = 1.0
    intercept: float = 0.0
    thickness_mm: float | None = None
    spacing_between_mm: float | None = None


def read_dicom_series(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """One DICOM series as HU (or raw values for another modality) with its geometry.

    Args:
        path: a folder of DICOM files, or one file of the series (the series is then read from
            the files in its folder).
        options: ``series_uid`` picks a series when the folder holds several; ``kind`` must be
            given for a modality other than CT; ``max_voxels`` limits the size.
        progress: unused: the slices are decoded as the converter reaches them, which reports
            its progress.

    Returns:
        data (Columns, Rows, slices), a :class:`~.slabs.SliceSource` that decodes a slice when
        it is read: ``data[i, j, k]`` is pixel (row j, column i) of the k-th slice along the
        normal; int16 HU when slopes and intercepts are integers and the values fit, else
        float32. spacing_mm (column spacing, row spacing, slice step); direction
        columns (row direction, column direction, normal); origin_mm the first slice's
        ImagePositionPatient.

    Raises:
        BoneFileError: no image files, several series and none chosen, slices that do not form
            one regular grid (missing, duplicated, tilted or mismatched slices), multi-frame
            files, undecodable pixel data, a non-CT series read with kind "auto", or too many
            voxels. Nothing is read past the first problem.
    """
    path = Path(path)
    if path.is_dir():
        folder, chosen_file = path, None
    elif path.is_file():
        folder, chosen_file = path.parent, path
    else:
        raise BoneFileError(path, "no such file or folder")

    slices, skipped = _scan_folder(folder, chosen_file)
    series_uid = _choose_series(path, slices, chosen_file, options.series_uid)
    members = [s for s in slices if s.series_uid == series_uid]
    first = _check_members(members)

    notes: list[str] = []
    other_series = {s.series_uid for s in slices} - {series_uid}
    if other_series:
        notes.append(f"series {series_uid} ({_series_summary(members)}); the folder holds "
                     f"{len(other_series)} other series")
    if skipped:
        notes.append(f"skipped {sum(skipped.values())} file(s) in the folder: "
                     f"{_skip_summary(skipped)}")

    if first.modality == "CT":
        kind = "ct"
    elif options.kind == "auto":
        modality = first.modality or "without a Modality"
        raise BoneFileError(path, f"the series is {modality}, not CT: HU thresholds do not "
                                  f"apply to its values. Pass kind explicitly ('ct', 'density' "
                                  "or 'labels') if that is what you mean")
    else:
        kind = "auto"  # the converter reads the values as options.kind says

    ordered, step_mm = _order_slices(path, members, notes)
    row_dir, col_dir, normal = _axes(first)
    spacing_in = (float(first.pixel_spacing_mm[1]), float(first.pixel_spacing_mm[0]))
    axes = np.column_stack((row_dir * spacing_in[0], col_dir * spacing_in[1], normal * step_mm))
    # IOP is rounded text: from_axes snaps the axes to the nearest rotation.
    spacing, direction = from_axes(ordered[0].path, axes)
    origin = np.array(ordered[0].position_mm, dtype=np.float64)

    shape = (first.cols, first.rows, len(ordered))
    check_size(path, shape, options)
    data = _hu_slices(ordered, shape)
    return RawVolume(path, "dicom", data, spacing, origin, direction, kind=kind, notes=notes)


# ---------------------------------------------------------------------------------------------
# First pass: headers


def _scan_folder(folder: Path, chosen_file: Path | None) -> tuple[list[_Slice], Counter]:
    """The image files in ``folder`` (not its subfolders) and why the others were skipped."""
    slices: list[_Slice] = []
    skipped: Counter = Counter()
    files = sorted(p for p in folder.iterdir() if not p.name.startswith(".") and p.is_file())
    for file in files:
        result = "DICOMDIR index" if file.name.upper() == "DICOMDIR" else _scan_file(file)
        if isinstance(result, str):
            if chosen_file is not None and file.samefile(chosen_file):
                raise BoneFileError(file, f"not a DICOM image slice: {result}")
            skipped[result] += 1
        else:
            slices.append(result)
    if not slices:
        what = f" ({sum(skipped.values())} file(s): {_skip_summary(skipped)})" if skipped \
            else ""
        raise BoneFileError(folder, f"no DICOM image files in the folder{what}")
    return slices, skipped


def _scan_file(file: Path) -> _Slice | str:
    """One file's header: a _Slice, or the reason it is not an image (a str).

    Raises:
        BoneFileError: a damaged DICOM file that cannot be told apart from a slice.
    """
    try:
        ds, forced, has_pixels = _read_header(file)
    except InvalidDicomError:
        return "not DICOM"
    except MemoryError:
        raise
    except Exception as exc:  # pydicom raises many types for damaged files
        raise BoneFileError(file, f"a damaged DICOM file: {exc}") from None
    try:
        return _classify(file, ds, forced, has_pixels)
    except (BoneFileError, MemoryError):
        raise
    except Exception as exc:  # values are decoded on access; bad ones raise assorted types
        if forced:
            return "not DICOM"  # a forced parse of a non-DICOM file can hold anything
        raise BoneFileError(file, f"a malformed DICOM header: {exc}") from None


def _classify(file: Path, ds: pydicom.Dataset, forced: bool, has_pixels: bool) -> _Slice | str:
    """A header read without error → a _Slice (perhaps with a problem) or a reason to skip."""
    meta = getattr(ds, "file_meta", None)
    meta_class = str(meta.get("MediaStorageSOPClassUID", "")) if meta is not None else ""
    sop_class = _text(ds, "SOPClassUID") or meta_class
    if MediaStorageDirectoryStorage in (meta_class, sop_class):
        return "DICOMDIR index"
    image_like = ("Rows" in ds or "ImagePositionPatient" in ds
                  or "Image Storage" in UID(sop_class or "0").name)
    if not has_pixels:
        if forced:
            return "not DICOM"
        if not image_like:
            return "not an image (no pixel data)"
    series_uid = _text(ds, "SeriesInstanceUID")
    if not has_pixels and not series_uid:
        # Truncated before its series was named, or a stray object: it cannot be matched to a
        # series. A lost slice of the loaded one is still caught by the step check.
        return "an image without pixel data or series (truncated?)"

    item = _Slice(path=file, forced=forced, series_uid=series_uid)
    try:
        skip = _fill(item, ds, has_pixels)
    except MemoryError:
        raise
    except Exception as exc:  # values are decoded on access; bad ones raise assorted types
        if forced:
            return "not DICOM"
        skip, item.problem = None, f"a malformed DICOM header: {exc}"
    if skip is not None:
        return skip
    if not series_uid:
        if item.problem is not None:
            raise BoneFileError(file, item.problem)
        item.series_uid = "(no SeriesInstanceUID)"
    return item


def _read_header(file: Path) -> tuple[pydicom.Dataset, bool, bool]:
    """(dataset without pixels, read with force, has pixel data).

    Files without the 128-byte preamble and "DICM" are only tried (with force) when named
    ``.dcm``: forcing every file in a folder would read notes and images as nonsense datasets.
    """
    forced = False
    with open(file, "rb") as f:
        try:
            ds = pydicom.dcmread(f, stop_before_pixels=True)
        except InvalidDicomError:
            if file.suffix.lower() != ".dcm":
                raise
            f.seek(0)
            try:
                ds = pydicom.dcmread(f, stop_before_pixels=True, force=True)
            except MemoryError:
                raise
            except Exception as exc:  # whatever a forced parse of junk raises
                raise InvalidDicomError(str(exc)) from None
            forced = True
        # stop_before_pixels rewinds to the Pixel Data element when there is one; a file that
        # ends first has none (or was cut off before it).
        has_pixels = f.read(2) in _PIXEL_GROUP
    meta = getattr(ds, "file_meta", None)
    if meta is not None and meta.get("TransferSyntaxUID") == DeflatedExplicitVRLittleEndian:
        # pydicom inflated the dataset into memory, so our file position says nothing.
        has_pixels = "Rows" in ds
    return ds, forced, has_pixels


def _fill(item: _Slice, ds: pydicom.Dataset, has_pixels: bool) -> str | None:
    """Copy what the series needs from ``ds`` into ``item``, or say why the file is not a slice
    (a str). Bad values raise (ValueError and others)."""
    item.modality = _text(ds, "Modality")
    item.description = _text(ds, "SeriesDescription")
    number = ds.get("SeriesNumber")
    item.series_number = int(number) if number not in (None, "") else None
    meta = getattr(ds, "file_meta", None)
    item.transfer_syntax = str(meta.get("TransferSyntaxUID", "")) if meta is not None else ""
    frames = ds.get("NumberOfFrames")
    item.frames = int(frames) if frames not in (None, "") else 1
    item.enhanced = item.frames > 1 or "PerFrameFunctionalGroupsSequence" in ds \
        or "SharedFunctionalGroupsSequence" in ds
    if not has_pixels:
        item.problem = "no pixel data (is the file truncated?)"
        return None
    if not item.enhanced and "ImagePositionPatient" not in ds:
        return "an image without ImagePositionPatient"  # a screenshot, scanned document...
    samples = int(ds.get("SamplesPerPixel", 1) or 1)
    if samples != 1:
        return "a colour image"  # a secondary capture or report, not a CT slice
    if "Rows" not in ds or "Columns" not in ds:
        item.problem = "pixel data without Rows and Columns"
        return None
    item.rows, item.cols = int(ds.Rows), int(ds.Columns)
    if item.enhanced:
        return None  # refused as a whole if its series is chosen
    item.position_mm = _numbers(ds, "ImagePositionPatient", 3)
    item.orientation = _numbers(ds, "ImageOrientationPatient", 6)
    item.pixel_spacing_mm = _numbers(ds, "PixelSpacing", 2)
    if item.pixel_spacing_mm is not None and not (item.pixel_spacing_mm > 0.0).all():
        item.problem = f"PixelSpacing {item.pixel_spacing_mm.tolist()} is not positive"
        return None
    item.thickness_mm = _positive(ds, "SliceThickness")
    item.spacing_between_mm = _positive(ds, "SpacingBetweenSlices")
    slope, intercept = ds.get("RescaleSlope"), ds.get("RescaleIntercept")
    if slope in (None, "") and "ModalityLUTSequence" in ds:
        item.problem = "a Modality LUT Sequence instead of RescaleSlope/Intercept (not supported)"
        return None
    item.slope = float(slope) if slope not in (None, "") else 1.0
    item.intercept = float(intercept) if intercept not in (None, "") else 0.0
    if not (np.isfinite(item.slope) and np.isfinite(item.intercept)) or item.slope == 0.0:
        item.problem = (f"RescaleSlope {item.slope:g} and RescaleIntercept "
                        f"{item.intercept:g} do not map pixels to values")
    return None


def _text(ds: pydicom.Dataset, keyword: str) -> str:
    value = ds.get(keyword)
    return "" if value is None else str(value).strip()


def _numbers(ds: pydicom.Dataset, keyword: str, count: int) -> np.ndarray | None:
    """A multi-valued decimal attribute as floats, None when absent; ValueError when wrong."""
    value = ds.get(keyword)
    if value is None or value == "":
        return None
    items = value if isinstance(value, (MultiValue, list, tuple)) else [value]
    values = np.array([float(v) for v in items], dtype=np.float64)
    if values.shape != (count,) or not np.isfinite(values).all():
        raise ValueError(f"{keyword} must be {count} finite numbers, got {value!r}")
    return values


def _positive(ds: pydicom.Dataset, keyword: str) -> float | None:
    """A length > 0 in mm, or None when absent, empty or not positive."""
    value = ds.get(keyword)
    if value in (None, ""):
        return None
    number = float(value)
    return number if np.isfinite(number) and number > 0.0 else None


# ---------------------------------------------------------------------------------------------
# Choosing the series and checking its slices


def _choose_series(
    path: Path, slices: list[_Slice], chosen_file: Path | None, wanted: str | None,
) -> str:
    """The UID of the series to load: the chosen file's, the one asked for, or the only one."""
    uids = {s.series_uid for s in slices}
    if chosen_file is not None:
        uid = next(s.series_uid for s in slices if s.path.samefile(chosen_file))
        if wanted is not None and wanted != uid:
            raise BoneFileError(path, f"the file belongs to series {uid}, not to the series_uid "
                                      f"{wanted} asked for")
        return uid
    if wanted is not None:
        if wanted not in uids:
            raise BoneFileError(path, f"no series {wanted} in the folder; it holds:\n"
                                      f"{_series_list(slices)}")
        return wanted
    if len(uids) > 1:
        raise BoneFileError(path, f"the folder holds {len(uids)} series; pick one with "
                                  f"series_uid (--series UID):\n{_series_list(slices)}")
    return next(iter(uids))


def _series_list(slices: list[_Slice]) -> str:
    groups: dict[str, list[_Slice]] = {}
    for s in slices:
        groups.setdefault(s.series_uid, []).append(s)
    order = sorted(groups, key=lambda uid: (groups[uid][0].series_number is None,
                                            groups[uid][0].series_number or 0, uid))
    return "\n".join(f"  {uid} ({_series_summary(groups[uid])})" for uid in order)


def _series_summary(members: list[_Slice]) -> str:
    first = members[0]
    parts = [first.modality or "no modality"]
    if first.description:
        parts.append(repr(first.description))
    if any(s.enhanced for s in members):
        parts.append(f"{len(members)} multi-frame file(s)")
    else:
        parts.append(f"{len(members)} slice{'s' if len(members) != 1 else ''}")
    return ", ".join(parts)


def _skip_summary(skipped: Counter) -> str:
    return ", ".join(f"{n} {reason}" for reason, n in skipped.most_common())


def _check_members(members: list[_Slice]) -> _Slice:
    """Refuse a series whose files are damaged, multi-frame or of different grids; return a
    slice with the series' common geometry."""
    for s in members:
        if s.problem is not None:
            raise BoneFileError(s.path, s.problem)
    enhanced = [s for s in members if s.enhanced]
    if enhanced:
        s = enhanced[0]
        raise BoneFileError(s.path, f"an enhanced multi-frame DICOM image ({s.frames} frame(s) "
                                    "in one file) is not supported: export the series as "
                                    "single-frame slices, or convert it to NIfTI (e.g. with "
                                    "dcm2niix) and load that")
    for s in members:
        for keyword, value in (("ImageOrientationPatient", s.orientation),
                               ("PixelSpacing", s.pixel_spacing_mm)):
            if value is None:
                raise BoneFileError(s.path, f"no {keyword}: the slice has no geometry")
    reference = _agree(members, "Rows", lambda s: np.array([s.rows]), 0.0)
    _agree(members, "Columns", lambda s: np.array([s.cols]), 0.0)
    _agree(members, "PixelSpacing", lambda s: s.pixel_spacing_mm, SAME_GEOMETRY_TOL)
    _agree(members, "ImageOrientationPatient", lambda s: s.orientation, SAME_GEOMETRY_TOL)
    return reference


def _agree(members: list[_Slice], keyword: str, value_of, tol: float) -> _Slice:
    """The slice holding the most common value of ``keyword``; BoneFileError names a slice that
    differs from it by more than ``tol``."""
    values = [np.asarray(value_of(s), dtype=np.float64) for s in members]
    # Rounded to the tolerance only to find the most common value; the test below is exact.
    keys = [tuple(np.round(v / tol).astype(np.int64)) if tol > 0 else tuple(v) for v in values]
    common_key, count = Counter(keys).most_common(1)[0]
    ref = keys.index(common_key)
    for s, v in zip(members, values, strict=True):
        if np.abs(v - values[ref]).max() > tol:
            raise BoneFileError(
                s.path, f"its {keyword} {_shown(v)} differs from {_shown(values[ref])} in "
                        f"{count} of the series' {len(members)} slices (e.g. "
                        f"{members[ref].path.name}): the files are not one stack of slices")
    return members[ref]


def _shown(x: np.ndarray) -> str:
    return f"{x[0]:g}" if x.size == 1 else f"[{', '.join(f'{a:g}' for a in x)}]"


def _axes(first: _Slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit row direction, column direction and slice normal (their cross product)."""
    iop = first.orientation
    row_dir, col_dir = iop[:3], iop[3:]
    for name, v in (("row", row_dir), ("column", col_dir)):
        norm = float(np.linalg.norm(v))
        if abs(norm - 1.0) > UNIT_VECTOR_TOL:
            raise BoneFileError(first.path, f"ImageOrientationPatient's {name} direction "
                                            f"{v.tolist()} is not a unit vector")
    row_dir = row_dir / np.linalg.norm(row_dir)
    col_dir = col_dir / np.linalg.norm(col_dir)
    normal = np.cross(row_dir, col_dir)
    length = float(np.linalg.norm(normal))
    if length < 0.5:  # not even 30° apart: from_axes would reject the shear anyway
        raise BoneFileError(first.path, f"ImageOrientationPatient {iop.tolist()}: the row and "
                                        "column directions are nearly parallel")
    return row_dir, col_dir, normal / length


def _order_slices(path: Path, members: list[_Slice], notes: list[str]) -> tuple[list[_Slice],
                                                                                  float]:
    """The slices sorted along the normal and the step between them, mm, after checking the
    step is uniform and the slices are stacked straight along the normal."""
    _, _, normal = _axes(members[0])
    positions = np.array([s.position_mm for s in members])
    along = positions @ normal
    order = np.argsort(along, kind="stable")
    ordered = [members[i] for i in order]
    along = along[order]
    positions = positions[order]
    if len(ordered) == 1:
        return ordered, _single_slice_step(ordered[0], notes)

    gaps = np.diff(along)
    for g, gap in enumerate(gaps):
        if gap < SAME_POSITION_MM:
            raise BoneFileError(
                ordered[g + 1].path,
                f"at the same position as {ordered[g].path.name} ({_where(positions[g])}): the "
                "series holds two copies of a slice, or several acquisitions, echoes or time "
                "points under one series UID; remove the extra files")
    step = float(np.median(gaps))
    tol = max(STEP_REL_TOL * step, min(STEP_ABS_TOL_MM, STEP_ABS_TOL_MAX_FRACTION * step))
    deviation = np.abs(gaps - step)
    worst = int(np.argmax(deviation))
    if deviation[worst] > tol:
        gap = float(gaps[worst])
        bad = int(np.count_nonzero(deviation > tol))
        between = (f"between {ordered[worst].path.name} at {along[worst]:.4g} mm and "
                   f"{ordered[worst + 1].path.name} at {along[worst + 1]:.4g} mm along the "
                   f"slice normal the gap is {gap:.4g} mm where the step is {step:.4g} mm")
        others = f" ({bad} irregular gaps in all)" if bad > 1 else ""
        if gap > step:
            missing = max(1, round(gap / step) - 1)
            problem = (f"slices are missing: {between}, about {missing} slice(s) missing"
                       f"{others}")
        else:
            problem = (f"the slices are unevenly spaced: {between}{others}; is an extra slice "
                       "or a second acquisition mixed in?")
        raise BoneFileError(path, problem)

    # Each origin must lie on the line through the first one along the normal; a sideways drift
    # is a sheared stack (a tilted CT gantry), which one spacing and direction cannot describe.
    offsets = positions - positions[0] - np.outer(along - along[0], normal)
    lateral = np.linalg.norm(offsets, axis=1)
    allowed = LATERAL_TOL_MM + MAX_SHEAR_COS * (along - along[0])
    k = int(np.argmax(lateral - allowed))
    if lateral[k] > allowed[k]:
        angle = np.degrees(np.arctan2(lateral[k], along[k] - along[0]))
        raise BoneFileError(
            ordered[k].path,
            f"the slice origins drift {lateral[k]:.3g} mm sideways over {along[k] - along[0]:.4g}"
            f" mm along the slice normal (slices sheared by {angle:.2f}°, as from a tilted CT "
            "gantry): resample the series onto a rectilinear grid first")
    return ordered, step


def _single_slice_step(s: _Slice, notes: list[str]) -> float:
    for keyword, value in (("SpacingBetweenSlices", s.spacing_between_mm),
                           ("SliceThickness", s.thickness_mm)):
        if value is not None:
            notes.append(f"a single slice: its step {value:g} mm is its {keyword}")
            return value
    raise BoneFileError(s.path, "a single slice without SpacingBetweenSlices or SliceThickness: "
                                "its thickness is unknown")


def _where(position: np.ndarray) -> str:
    return f"({', '.join(f'{x:.4g}' for x in position)}) mm"


# ---------------------------------------------------------------------------------------------
# Second pass: pixels


def _hu_slices(ordered: list[_Slice], shape: tuple[int, int, int]) -> SliceSource:
    """The series as a source that decodes a slice and rescales it to HU when the converter
    reaches it: (Columns, Rows) per slice, int16 HU when slopes and intercepts are integers
    and the slice's values fit, else float32."""
    integral = all(float(s.slope).is_integer() and float(s.intercept).is_integer()
                   for s in ordered)

    def read(k: int) -> np.ndarray:
        s = ordered[k]
        pixels = _read_pixels(s)
        if integral and np.issubdtype(pixels.dtype, np.integer):
            hu = pixels.astype(np.int64) * int(s.slope) + int(s.intercept)
            if INT16_MIN <= hu.min() and hu.max() <= INT16_MAX:
                return hu.astype(np.int16).T  # pixel (row j, column i) → data[i, j, k]
            return hu.astype(np.float32).T
        return (pixels.astype(np.float64) * s.slope + s.intercept).astype(np.float32).T

    # A slice is decoded whole: its pixels, their int64 HU and the result.
    slice_bytes = shape[0] * shape[1] * (2 + 8 + 4)
    return SliceSource(read, shape, np.int16 if integral else np.float32, slice_bytes)


def _read_pixels(s: _Slice) -> np.ndarray:
    """The slice's stored pixel values, (Rows, Columns)."""
    syntax = UID(s.transfer_syntax).name if s.transfer_syntax else "unknown transfer syntax"
    try:
        ds = pydicom.dcmread(s.path, force=s.forced)
        pixels = ds.pixel_array
    except MemoryError:
        raise
    except Exception as exc:  # decoder plugins raise whatever they like
        raise BoneFileError(s.path, f"cannot decode its pixel data ({syntax}): {exc}") from None
    if pixels.shape != (s.rows, s.cols):
        raise BoneFileError(s.path, f"its pixel data has shape {pixels.shape}, not the "
                                    f"{s.rows} × {s.cols} its header says")
    return pixels
