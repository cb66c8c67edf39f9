"""NIfTI volumes (``.nii``, ``.nii.gz``) with nibabel."""

from __future__ import annotations

import zlib
from pathlib import Path

import nibabel as nib
import numpy as np
from nibabel.filebasedimages import ImageFileError

from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import from_axes, mm_per_unit, to_lps
from .volume import Progress, RawVolume

#: NIfTI intent code of a label map.
NIFTI_INTENT_LABEL = 1002


def read_nifti(path: Path, options: LoadOptions, progress: Progress | None) -> RawVolume:
    """A NIfTI-1 or NIfTI-2 volume; its affine (RAS) is converted to LPS."""
    try:
        image = nib.load(str(path))
    except (ImageFileError, nib.spatialimages.HeaderDataError, ValueError, EOFError,
            zlib.error) as exc:
        raise BoneFileError(path, f"not a valid NIfTI file: {exc}") from None
    shape = tuple(int(n) for n in image.shape)
    while len(shape) > 3 and shape[-1] == 1:  # a 3-D volume stored as 4-D with one frame
        shape = shape[:-1]
    check_size(path, shape, options)
    if progress is not None:
        progress("reading", 0, 1)
    try:
        # dataobj applies scl_slope/scl_inter when they are set, and only then makes floats.
        data = np.asanyarray(image.dataobj).reshape(shape)
    except (ValueError, EOFError, zlib.error, OSError) as exc:
        raise BoneFileError(path, f"the voxel data is damaged or truncated: {exc}") from None
    if progress is not None:
        progress("reading", 1, 1)
    header = image.header
    notes = []
    unit = header.get_xyzt_units()[0]
    if unit in (None, "unknown"):
        scale = 1.0
        notes.append("no spatial unit in the header: millimetres assumed")
    else:
        scale = mm_per_unit(path, {"meter": "m", "micron": "um"}.get(unit, unit))
        if scale != 1.0:
            notes.append(f"converted from {unit} to mm")
    # The header stores float32: take each value's shortest decimal (0.2, not 0.2000000030),
    # which is what the writer meant whenever it wrote a decimal.
    affine = np.array([float(np.format_float_positional(np.float32(v), unique=True))
                       for v in np.asarray(image.affine).ravel()]).reshape(4, 4)
    spacing, direction = from_axes(path, affine[:3, :3] * scale)
    origin, direction = to_lps(affine[:3, 3] * scale, direction, "RAS")
    notes.append("converted from RAS to LPS")
    if int(header["sform_code"]) == 0 and int(header["qform_code"]) == 0:
        notes.append("the file gives no orientation (sform and qform codes 0): spacing from "
                     "pixdim, but the origin and axes are nibabel's guess — place the bone "
                     "yourself")
    intent = int(header["intent_code"])
    kind = "labels" if intent == NIFTI_INTENT_LABEL else "auto"
    return RawVolume(path, "nifti", data, spacing, origin, direction, kind=kind, notes=notes)
