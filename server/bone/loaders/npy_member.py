"""Reading arrays from .npy files and .npz members with the size checked before the data."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .errors import BoneFileError

#: Array element types a bone file may hold (never objects: no pickles).
ALLOWED_KINDS = "biuf"
#: Small arrays (spacing, origin, direction, JSON) — anything bigger is not metadata.
MAX_META_ELEMENTS = 1 << 20


def _header(path: Path, f: BinaryIO, what: str) -> tuple[tuple[int, ...], np.dtype]:
    try:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(f)
    except ValueError as exc:
        raise BoneFileError(path, f"{what} is not a valid .npy array: {exc}") from None
    if dtype.kind not in ALLOWED_KINDS or dtype.hasobject:
        raise BoneFileError(path, f"{what} holds {dtype} values; a bone file holds numbers")
    return tuple(shape), dtype


def read_npy_array(path: Path, max_elements: int) -> np.ndarray:
    """The array in a .npy file, refusing more than ``max_elements`` before reading it."""
    with open(path, "rb") as f:
        shape, dtype = _header(path, f, "the file")
        _check_count(path, "the file", shape, max_elements)
        data_start = f.tell()
        f.seek(0, 2)
        need = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        if f.tell() - data_start < need:
            raise BoneFileError(path, f"the file is truncated: {f.tell() - data_start} bytes of "
                                      f"voxel data where {shape} {dtype} needs {need}")
        f.seek(0)
        return np.lib.format.read_array(f, allow_pickle=False)


def read_member(
    path: Path, archive: zipfile.ZipFile, key: str, max_elements: int,
) -> np.ndarray:
    """Array ``key`` of an open .npz archive, refusing more than ``max_elements``."""
    name = key + ".npy"
    what = f"array {key!r}"
    try:
        with archive.open(name) as f:
            shape, _ = _header(path, f, what)
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
