"""Reading arrays from .npy files and .npz members with the size checked before the data:
small arrays whole, volumes as sources read a block at a time (``slabs.StreamSource``)."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .errors import BoneFileError
from .payload import Payload
from .slabs import StreamSource

#: Array element types a bone file may hold (never objects: no pickles).
ALLOWED_KINDS = "biuf"
#: Small arrays (spacing, origin, direction, JSON) — anything bigger is not metadata.
MAX_META_ELEMENTS = 1 << 20


def _header(path: Path, f: BinaryIO, what: str) -> tuple[tuple[int, ...], np.dtype, bool]:
    """(shape, dtype, Fortran order) of the .npy array ``f`` is at the start of."""
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
    except ValueError as exc:
        raise BoneFileError(path, f"{what} is not a valid .npy array: {exc}") from None
    if dtype.kind not in ALLOWED_KINDS or dtype.hasobject:
        raise BoneFileError(path, f"{what} holds {dtype} values; a bone file holds numbers")
    return tuple(shape), dtype, bool(fortran)


def npy_source(path: Path, max_elements: int) -> StreamSource:
    """The volume in a .npy file, read a block at a time; refused past ``max_elements`` or
    when the file is shorter than its header says, before a value is read."""
    with open(path, "rb") as f:
        shape, dtype, fortran = _header(path, f, "the file")
        _check_count(path, "the file", shape, max_elements)
        data_start = f.tell()
        f.seek(0, 2)
        need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if f.tell() - data_start < need:
            raise BoneFileError(path, f"the file is truncated: {f.tell() - data_start} bytes of "
                                      f"voxel data where {shape} {dtype} needs {need}")
    return StreamSource(Payload(path, path, data_start, "raw", need), _three(path, shape),
                        dtype, fortran)


def member_source(path: Path, archive: zipfile.ZipFile, key: str,
                  max_elements: int) -> StreamSource:
    """Volume ``key`` of an open .npz archive as a source that reads (and inflates) the member
    a block at a time, reopening the archive for each pass."""
    name = key + ".npy"
    what = f"array {key!r}"
    try:
        with archive.open(name) as f:
            shape, dtype, fortran = _header(path, f, what)
            header_bytes = f.tell()
        info = archive.getinfo(name)
    except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as exc:
        raise BoneFileError(path, f"{what} is damaged or truncated: {exc}") from None
    _check_count(path, what, shape, max_elements)
    need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if info.file_size - header_bytes < need:
        raise BoneFileError(path, f"{what} is truncated: {info.file_size - header_bytes} "
                                  f"bytes of values where {shape} {dtype} needs {need}")
    return StreamSource(_Member(path, name, header_bytes, need, what), _three(path, shape),
                        dtype, fortran)


def _three(path: Path, shape: tuple[int, ...]) -> tuple[int, int, int]:
    if len(shape) != 3:
        raise BoneFileError(path, f"a bone volume is 3-D; this one has shape {tuple(shape)}")
    return shape  # type: ignore[return-value]


class _Member:
    """A .npz member's values: the archive opened anew for each pass over them."""

    def __init__(self, path: Path, name: str, skip: int, size: int, what: str) -> None:
        self.path, self.name, self.skip, self.size, self.what = path, name, skip, size, what

    def open(self) -> _MemberReader:
        archive = zipfile.ZipFile(self.path)
        try:
            f = archive.open(self.name)
            f.read(self.skip)
        except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as exc:
            archive.close()
            raise BoneFileError(self.path, f"{self.what} is damaged or truncated: "
                                           f"{exc}") from None
        return _MemberReader(self, archive, f)


class _MemberReader:
    def __init__(self, member: _Member, archive: zipfile.ZipFile, f: BinaryIO) -> None:
        self.member, self.archive, self.f = member, archive, f

    def readinto(self, view: memoryview) -> None:
        filled = 0
        try:
            while filled < len(view):
                n = self.f.readinto(view[filled:])
                if not n:
                    break
                filled += n
        except (zipfile.BadZipFile, EOFError, ValueError, OSError) as exc:
            raise BoneFileError(self.member.path, f"{self.member.what} is damaged or "
                                                  f"truncated: {exc}") from None
        if filled < len(view):
            raise BoneFileError(self.member.path, f"{self.member.what} is truncated")

    def finish(self) -> None:
        pass  # the zip's own size ends the member

    def close(self) -> None:
        self.f.close()
        self.archive.close()


def read_member(
    path: Path, archive: zipfile.ZipFile, key: str, max_elements: int,
) -> np.ndarray:
    """Array ``key`` of an open .npz archive, refusing more than ``max_elements``."""
    name = key + ".npy"
    what = f"array {key!r}"
    try:
        with archive.open(name) as f:
            shape, _, _ = _header(path, f, what)
        _check_count(path, what, shape, max_elements)
        with archive.open(name) as f:
            return np.lib.format.read_array(f, allow_pickle=False)
    except BoneFileError:
        raise
    except (zipfile.BadZipFile, EOFError, ValueError, OSError) as exc:
        raise BoneFileError(path, f"{what} is damaged or truncated: {exc}") from None


def _check_count(path: Path, what: str, shape: tuple[int, ...], max_elements: int) -> None:
    count = int(np.prod(np.asarray(shape, dtype=np.int64)))
    if count > max_elements:
        raise BoneFileError(path, f"{what} has shape {shape} ({count:,} values), more than "
                                  f"the {max_elements:,} allowed")
