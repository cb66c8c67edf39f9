"""Bone files in: CT and segmentation loaders, and our own compact format.

``load_bone(path)`` reads any supported file or folder into a :class:`~..bone.Bone`, keeping
spacing, origin and orientation (world frame: LPS millimetres). Formats:

- ``.npy`` (one array; spacing from the caller) and ``.npz`` (arrays ``density``, ``labels``
  or ``hu`` with ``spacing_mm``, ``origin_mm``, ``direction``);
- NRRD (``.nrrd``, ``.nhdr``) with pynrrd, including 3D Slicer ``.seg.nrrd`` segmentations;
- NIfTI (``.nii``, ``.nii.gz``) with nibabel;
- DICOM series (a folder, or one file of the series) with pydicom;
- PNG slice stacks (a folder of ``*.png``; spacing from the caller);
- burrforce's own format (``.bone.npz``), written by :func:`save_bone`.

Every failure is a :class:`BoneFileError` naming the file and the problem, raised before
anything is returned; :class:`BoneTooLarge` (one of them) when the load would take more memory
than its budget (``LoadOptions.memory_budget_bytes``), raised from the header. The voxels are
read and converted a slab at a time (``slabs``): a source is never held whole.
"""

from __future__ import annotations

from pathlib import Path

from ..bone import Bone
from .budget import BoneTooLarge
from .compact import BONE_SUFFIX, save_bone, write_bone
from .convert import LoadOptions, to_bone
from .errors import BoneFileError
from .volume import MAX_LOAD_VOXELS, Progress, RawVolume

FORMATS = ("bone", "npy", "npz", "nrrd", "nifti", "dicom", "png")

__all__ = [
    "BONE_SUFFIX",
    "FORMATS",
    "MAX_LOAD_VOXELS",
    "BoneFileError",
    "BoneTooLarge",
    "LoadOptions",
    "Progress",
    "RawVolume",
    "detect_format",
    "load_bone",
    "save_bone",
    "write_bone",
]


def detect_format(path: str | Path) -> str:
    """The format of ``path`` from its name, or for a folder from what it holds."""
    path = Path(path)
    if path.is_dir():
        return _folder_format(path)
    if not path.exists():
        raise BoneFileError(path, "no such file or folder")
    name = path.name.lower()
    if name.endswith(BONE_SUFFIX):
        return "bone"
    for suffix, fmt in ((".npy", "npy"), (".npz", "npz"), (".nrrd", "nrrd"), (".nhdr", "nrrd"),
                        (".nii", "nifti"), (".nii.gz", "nifti"), (".dcm", "dicom"),
                        (".png", "png")):
        if name.endswith(suffix):
            return fmt
    with open(path, "rb") as f:
        head = f.read(132)
    if head[128:132] == b"DICM":
        return "dicom"
    raise BoneFileError(path, "unknown bone format (known: .bone.npz, .npy, .npz, .nrrd, "
                              ".nhdr, .seg.nrrd, .nii, .nii.gz, a DICOM series, a folder of "
                              "PNG slices)")


def load_bone(
    path: str | Path, options: LoadOptions | None = None, progress: Progress | None = None,
) -> Bone:
    """Read a bone file or folder.

    Args:
        path: the file, or the folder of a DICOM series or PNG stack.
        options: kind, spacing for formats without one, materials file, DICOM series.
        progress: called as progress(stage, done, total) while reading and converting.

    Raises:
        BoneFileError: the file is missing, unreadable, malformed or not a bone volume.
    """
    path = Path(path)
    options = options or LoadOptions()
    fmt = detect_format(path)
    try:
        if fmt in ("bone", "npz"):
            from .numpy_file import read_npz
            result = read_npz(path, options)
            if isinstance(result, Bone):  # our own format: already a bone
                return result
            raw = result
        elif fmt == "npy":
            from .numpy_file import read_npy
            raw = read_npy(path, options)
        elif fmt == "nrrd":
            from .nrrd_file import read_nrrd
            raw = read_nrrd(path, options, progress)
        elif fmt == "nifti":
            from .nifti_file import read_nifti
            raw = read_nifti(path, options, progress)
        elif fmt == "dicom":
            from .dicom_series import read_dicom_series
            raw = read_dicom_series(path, options, progress)
        else:
            from .png_stack import read_png_stack
            raw = read_png_stack(path, options, progress)
        return to_bone(raw, options, progress)
    except BoneFileError:
        raise
    except MemoryError:
        raise BoneFileError(path, "not enough memory to load it") from None
    except (OSError, EOFError) as exc:
        raise BoneFileError(path, f"cannot read it: {exc}") from None
    except Exception as exc:
        # The format libraries meet corrupt bytes with any exception (zlib.error,
        # StopIteration, NotImplementedError, struct.error, …): at this edge every one of them
        # means the file is damaged. The type stays in the message for diagnosis.
        raise BoneFileError(path, f"damaged or not a valid {fmt} file "
                                  f"({type(exc).__name__}: {exc})") from exc


def _folder_format(path: Path) -> str:
    entries = [p for p in path.iterdir() if not p.name.startswith(".")]
    files = [p for p in entries if p.is_file()]
    if not files:
        if entries:
            raise BoneFileError(path, "the folder holds only sub-folders: point at the folder "
                                      "of one series or one PNG stack")
        raise BoneFileError(path, "the folder is empty")
    # DICOM first: a series folder may hold a stray thumbnail, a PNG stack never holds DICOM.
    for p in files:
        if p.suffix.lower() == ".dcm":
            return "dicom"
        with open(p, "rb") as f:
            if f.read(132)[128:132] == b"DICM":
                return "dicom"
    if any(p.suffix.lower() == ".png" for p in files):
        return "png"
    raise BoneFileError(path, "the folder holds neither PNG slices nor DICOM files")
