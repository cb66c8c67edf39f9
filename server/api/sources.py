"""Where a session's bone comes from, checked before anything is loaded.

A source is a string:

- ``phantom:NAME`` — a built-in phantom (``bone.PHANTOMS``), optional ``voxel_mm``;
- ``library:RELATIVE/PATH`` — a file or DICOM/PNG folder in the configured bone library;
- ``upload:ID`` — a file uploaded through the API;
- ``snapshot:NAME`` — a snapshot taken of a session (``.bone.npz``).

Files whose voxels could mean several things (npy, npz, NRRD, NIfTI, PNG) need ``kind``
(``ct``, ``labels`` or ``density``): over REST nobody is at a terminal to read the loader's
guess, and a CT read as labels is a wrong bone, not an error.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ..bone import PHANTOMS, Bone, load_bone, phantom
from ..bone.loaders import BoneFileError, LoadOptions, Progress, detect_format
from .errors import ApiError, BadName, Invalid, NotFound

KINDS = ("ct", "labels", "density")
#: Formats that say what their voxels are: DICOM is CT, .bone.npz is ours.
SELF_DESCRIBING = ("dicom", "bone")
UPLOAD_ID = re.compile(r"^[0-9a-f]{16}$")
SNAPSHOT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
SNAPSHOT_SUFFIX = ".bone.npz"


class SourceError(ValueError):
    """A source that cannot be used: the message says why; ``error`` is the domain error it
    is answered as (``errors``: Invalid, NotFound, BadName)."""

    def __init__(self, message: str, error: type[ApiError] = Invalid) -> None:
        super().__init__(message)
        self.error = error

    def as_api_error(self) -> ApiError:
        return self.error(str(self))


@dataclass(frozen=True)
class BoneSource:
    """A resolved source: what to load and how.

    Attributes:
        source: the string as given (``phantom:temporal``, ``library:ct/head.nrrd``, …).
        path: the file or folder, None for a phantom.
        kind: what the voxels are (None: the format says).
        voxel_mm: a phantom's voxel size (None: its default).
        spacing_mm: voxel size for formats without one (npy, PNG).
    """

    source: str
    path: Path | None = None
    kind: str | None = None
    voxel_mm: float | None = None
    spacing_mm: tuple[float, float, float] | None = None

    def load(self, progress: Progress | None = None,
             memory_budget_bytes: int | None = None) -> Bone:
        """Load it (seconds for a large CT) within ``memory_budget_bytes`` (None: the bone's
        bytes + 512 MiB). Raises BoneFileError/ValueError on bad data, ``BoneTooLarge`` (a
        BoneFileError) for a file too large for the budget."""
        if self.path is None:
            return phantom(self.source.split(":", 1)[1], self.voxel_mm)
        options = LoadOptions(kind=self.kind or "auto", spacing_mm=self.spacing_mm,
                              memory_budget_bytes=memory_budget_bytes)
        return load_bone(self.path, options, progress)


@dataclass(frozen=True)
class SourceRoots:
    """The folders sources resolve in."""

    library: Path | None
    uploads: Path
    snapshots: Path


def resolve(source: str, roots: SourceRoots, kind: str | None = None,
            voxel_mm: float | None = None,
            spacing_mm: tuple[float, float, float] | None = None) -> BoneSource:
    """Check ``source`` and return what to load.

    Raises:
        SourceError: unknown scheme or phantom, a path outside its folder, a missing file
            (NotFound), or an ambiguous format without ``kind``.
    """
    if not isinstance(source, str) or ":" not in source:
        raise SourceError(f"bone source {source!r} must be phantom:NAME, library:PATH, "
                          "upload:ID or snapshot:NAME")
    scheme, name = source.split(":", 1)
    if kind is not None and kind not in KINDS:
        raise SourceError(f"kind must be one of {', '.join(KINDS)}, got {kind!r}")
    if scheme == "phantom":
        if name not in PHANTOMS:
            raise SourceError(f"unknown phantom {name!r}; built in: {', '.join(PHANTOMS)}",
                              NotFound)
        if kind is not None or spacing_mm is not None:
            raise SourceError("kind and spacing_mm are for files; a phantom takes voxel_mm")
        return BoneSource(source, voxel_mm=voxel_mm)
    if voxel_mm is not None:
        raise SourceError("voxel_mm sets a phantom's voxel size; a file has its own "
                          "(spacing_mm sets it for npy and PNG files)")
    if scheme == "library":
        if roots.library is None:
            raise SourceError("no bone library is configured (serve --bone-library DIR)", NotFound)
        path = inside(roots.library, name)
    elif scheme == "upload":
        if not UPLOAD_ID.match(name):
            raise SourceError(f"upload id {name!r} is not one this server issued", NotFound)
        matches = sorted(roots.uploads.glob(name + ".*"))
        if not matches:
            raise SourceError(f"no upload {name}", NotFound)
        path = matches[0]
    elif scheme == "snapshot":
        path = snapshot_path(roots.snapshots, name)
        if not path.is_file():
            raise SourceError(f"no snapshot {name!r}", NotFound)
        return BoneSource(source, path)
    else:
        raise SourceError(f"unknown bone source scheme {scheme!r}: phantom, library, upload "
                          "or snapshot")
    return file_source(source, path, kind, spacing_mm)


def file_source(source: str, path: Path, kind: str | None = None,
                spacing_mm: tuple[float, float, float] | None = None) -> BoneSource:
    """A bone file or series folder as a source, once its format says what its voxels are or
    ``kind`` does. Raises SourceError (NotFound for a missing file)."""
    try:
        fmt = detect_format(path)
    except BoneFileError as exc:
        raise SourceError(str(exc), NotFound if not path.exists() else Invalid) from None
    if kind is None and fmt not in SELF_DESCRIBING:
        raise SourceError(f"{source} is a {fmt} file, whose voxels could be CT numbers, labels "
                          f"or densities: say which with kind ({', '.join(KINDS)})")
    return BoneSource(source, path, kind, None, spacing_mm)


def inside(root: Path, name: str) -> Path:
    """``root/name``, refusing anything that leaves ``root`` (``..``, absolute paths, symbolic
    links pointing out). Raises SourceError (NotFound for a missing file)."""
    if not name or name.startswith(("/", "\\")) or "\x00" in name:
        raise SourceError(f"library path {name!r} must be relative to the library", BadName)
    base = root.resolve()
    path = (base / name).resolve()
    if path != base and base not in path.parents:
        raise SourceError(f"library path {name!r} leaves the library", BadName)
    if not path.exists():
        raise SourceError(f"no {name!r} in the bone library", NotFound)
    return path


def snapshot_path(root: Path, name: str) -> Path:
    if not SNAPSHOT_NAME.match(name) or ".." in name:
        raise SourceError(f"snapshot name {name!r}: letters, digits, '_', '-', '.' only", BadName)
    if not name.endswith(SNAPSHOT_SUFFIX):
        name += SNAPSHOT_SUFFIX
    return root / name


def library_entries(root: Path | None, limit: int = 1000) -> list[dict]:
    """Bone files and series folders in the library (relative paths, formats, sizes)."""
    if root is None or not root.is_dir():
        return []
    out: list[dict] = []
    base = root.resolve()
    for path in sorted(base.rglob("*")):
        if len(out) >= limit:
            break
        if path.name.startswith(".") or any(p.name.startswith(".") for p in path.parents
                                            if p != base and base in p.parents):
            continue
        try:
            fmt = detect_format(path)
        except (BoneFileError, OSError):
            continue
        if path.is_file() and path.parent != base and fmt in ("dicom", "png") and \
                _is_series_member(path):
            continue  # listed as its folder
        size = (path.stat().st_size if path.is_file()
                else sum(p.stat().st_size for p in path.iterdir() if p.is_file()))
        out.append({"source": f"library:{path.relative_to(base).as_posix()}", "format": fmt,
                    "folder": path.is_dir(), "bytes": size,
                    "needs_kind": fmt not in SELF_DESCRIBING})
    return out


def _is_series_member(path: Path) -> bool:
    try:
        return detect_format(path.parent) in ("dicom", "png")
    except (BoneFileError, OSError):
        return False
