"""NIfTI volumes (``.nii``, ``.nii.gz``): the header with nibabel, the voxels a block at a
time (``slabs.StreamSource``), scaled as nibabel scales them."""

from __future__ import annotations

import gzip
import zlib
from pathlib import Path

import nibabel as nib
import numpy as np
from nibabel.filebasedimages import ImageFileError
from nibabel.volumeutils import apply_read_scaling

from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import from_axes, mm_per_unit, to_lps
from .payload import Payload
from .slabs import StreamSource
from .volume import Progress, RawVolume

#: NIfTI intent code of a label map.
NIFTI_INTENT_LABEL = 1002
#: sizeof_hdr of each NIfTI version, and its header's layout in nibabel.
HEADER_SIZES = {348: nib.nifti1.header_dtype, 540: nib.nifti2.header_dtype}


def read_nifti(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """A NIfTI-1 or NIfTI-2 volume; its affine (RAS) is converted to LPS."""
    raw = _raw_header(path)
    try:
        image = nib.load(str(path))
    except (ImageFileError, nib.spatialimages.HeaderDataError, ValueError, EOFError,
            zlib.error) as exc:
        raise BoneFileError(path, f"not a valid NIfTI file: {exc}") from None
    shape = tuple(int(n) for n in image.shape)
    while len(shape) > 3 and shape[-1] == 1:  # a 3-D volume stored as 4-D with one frame
        shape = shape[:-1]
    check_size(path, shape, options)
    header = image.header
    data = _voxels(path, image, shape)
    notes = []
    unit = header.get_xyzt_units()[0]
    if unit in (None, "unknown"):
        scale = 1.0
        notes.append("no spatial unit in the header: millimetres assumed")
    else:
        scale = mm_per_unit(path, {"meter": "m", "micron": "um"}.get(unit, unit))
        if scale != 1.0:
            notes.append(f"converted from {unit} to mm")
    sform, qform = int(raw["sform_code"]), int(raw["qform_code"])
    pixdim = [float(v) for v in raw["pixdim"][1:4]]
    if sform == 0 and not all(v != 0.0 for v in pixdim):
        # qform and the no-orientation fallback take the voxel size from pixdim; nibabel
        # would silently make a 0 there 1 mm.
        if options.spacing_mm is None:
            raise BoneFileError(path, f"the header gives no voxel size: pixdim[1:4] is "
                                      f"{pixdim} and there is no sform; give spacing_mm")
        notes.append(f"the header gives no voxel size (pixdim[1:4] {pixdim}, no sform)")
    # The header stores float32: take each value's shortest decimal (0.2, not 0.2000000030),
    # which is what the writer meant whenever it wrote a decimal.
    affine = np.array([float(np.format_float_positional(np.float32(v), unique=True))
                       for v in np.asarray(image.affine).ravel()]).reshape(4, 4)
    spacing, direction = from_axes(path, affine[:3, :3] * scale)
    origin, direction = to_lps(affine[:3, 3] * scale, direction, "RAS")
    notes.append("converted from RAS to LPS")
    if sform == 0 and qform == 0:
        notes.append("the file gives no orientation (sform and qform codes 0): spacing from "
                     "pixdim, but the origin and axes are nibabel's guess — place the bone "
                     "yourself")
    intent = int(header["intent_code"])
    kind = "labels" if intent == NIFTI_INTENT_LABEL else "auto"
    return RawVolume(path, "nifti", data, spacing, origin, direction, kind=kind, notes=notes)


def _raw_header(path: Path) -> np.ndarray:
    """The header as stored, before nibabel mends it (a 0 pixdim becomes 1 there), checked
    for what tells a NIfTI header: its size and its number of dimensions."""
    try:
        opener = gzip.open if path.name.lower().endswith(".gz") else open
        with opener(path, "rb") as f:
            head = f.read(540)
    except (OSError, EOFError, zlib.error) as exc:
        raise BoneFileError(path, f"not a valid NIfTI file: {exc}") from None
    for size, layout in HEADER_SIZES.items():
        for order in "<>":
            if len(head) >= size and int.from_bytes(head[:4], "little" if order == "<"
                                                    else "big") == size:
                raw = np.frombuffer(head[:size], layout.newbyteorder(order))[0]
                ndim = int(raw["dim"][0])
                if not 1 <= ndim <= 7:
                    raise BoneFileError(path, f"not a valid NIfTI header: dim[0] (the "
                                              f"number of dimensions) is {ndim}, not 1–7")
                return raw
    first = int.from_bytes(head[:4], "little") if len(head) >= 4 else None
    raise BoneFileError(path, f"not a valid NIfTI header: it begins with sizeof_hdr {first}, "
                              "not 348 (NIfTI-1) or 540 (NIfTI-2)")


def _voxels(path: Path, image, shape: tuple[int, ...]) -> StreamSource:
    """The voxels as a source: read from the file (inflated from a ``.nii.gz``) a block at
    a time, scaled by scl_slope and scl_inter as nibabel's ``dataobj`` scales them."""
    header = image.header
    dtype = np.dtype(header.get_data_dtype())
    if dtype.fields is not None or dtype.kind not in "biuf":
        raise BoneFileError(path, f"the voxels are {dtype} values; a bone volume holds "
                                  "numbers")
    offset = int(image.dataobj.offset)  # the header says 0 when it is the minimum
    size = int(np.prod(image.shape, dtype=np.int64)) * dtype.itemsize
    if path.name.lower().endswith(".gz"):
        payload = Payload(path, path, 0, "gzip", size, skip=offset)
    else:
        payload = Payload(path, path, offset, "raw", size)
    payload.check()
    slope, inter = np.asanyarray(image.dataobj.slope), np.asanyarray(image.dataobj.inter)
    if np.can_cast(inter, slope.dtype):
        inter = inter.astype(slope.dtype)

    def scaled(values: np.ndarray) -> np.ndarray:
        return apply_read_scaling(values, slope, inter)

    out_dtype = scaled(np.zeros(1, dtype=dtype.newbyteorder("="))).dtype
    return StreamSource(payload, shape, dtype, fortran=True, transform=scaled,
                        out_dtype=out_dtype)
