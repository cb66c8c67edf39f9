"""Large, highly compressible bone files written a slab at a time: what a memory bound on
loading is measured with (``bench load-while-streaming --file``, tests/test_load_memory.py).

- :func:`write_ct`: a float64 CT of size³ voxels — air (−1000 HU) with a cube of cortical
  bone (1200 HU) in the middle — as a gzip NRRD or ``.nii.gz``: a 1024³ one (8 GiB of
  values) is a few megabytes.
- :func:`write_bomb`: a uint8 NRRD or ``.nii.gz`` whose header declares size³ voxels and
  whose gzip data inflates to ``inflated_bytes`` of zeros (8 GiB in ~8 MB).

Writing never holds more than one slab: a slab that repeats one already compressed is not
compressed again (after a full flush deflate starts afresh, so equal input gives equal
bytes), and the gzip header and trailer (CRC-32 and size) are written by hand around the raw
deflate stream.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

AIR_HU = -1000.0
BONE_HU = 1200.0
#: Values per slab while writing (64 MiB of float64).
SLAB_VALUES = 8 << 20
SUFFIXES = {"nrrd": ".nrrd", "nifti": ".nii.gz"}


def write_ct(path: Path, size: int, fmt: str = "nrrd", voxel_mm: float = 0.5) -> Path:
    """A float64 CT of ``size``³ voxels at ``path`` (``fmt``: "nrrd" or "nifti"): air with a
    bone cube of half the edge in the middle."""
    lo, hi = size // 4, size - size // 4

    def slabs() -> Iterator[tuple[str, bytes]]:
        # Fortran order: a slab is whole slices k, each (x, y) slice x-fastest.
        per = max(SLAB_VALUES // (size * size), 1)
        air_slice = np.full((size, size), AIR_HU)
        bone_slice = air_slice.copy()
        bone_slice[lo:hi, lo:hi] = BONE_HU
        made: dict[str, bytes] = {}  # a slab of one kind of slice, made once
        for k0 in range(0, size, per):
            k1 = min(k0 + per, size)
            kinds = ["bone" if lo <= k < hi else "air" for k in range(k0, k1)]
            key = f"{kinds[0]}-{k1 - k0}" if len(set(kinds)) == 1 else ""
            data = made.get(key) if key else None
            if data is None:
                data = np.stack([bone_slice if kind == "bone" else air_slice
                                 for kind in kinds], axis=2).tobytes(order="F")
                if key:
                    made[key] = data
            yield key, data

    header = _header(fmt, size, "double", np.float64, voxel_mm)
    return _write_gzip(path, header, slabs(), fmt)


def write_bomb(path: Path, size: int, inflated_bytes: int, fmt: str = "nrrd") -> Path:
    """A uint8 file declaring ``size``³ voxels whose gzip data inflates to
    ``inflated_bytes`` of zeros (the header's bytes included for a ``.nii.gz``)."""
    header = _header(fmt, size, "uint8", np.uint8, 1.0)
    payload = inflated_bytes - (len(header) if fmt == "nifti" else 0)
    chunk = b"\0" * (64 << 20)

    def slabs() -> Iterator[tuple[str, bytes]]:
        left = payload
        while left > 0:
            n = min(left, len(chunk))
            yield (f"zeros-{n}", chunk if n == len(chunk) else chunk[:n])
            left -= n

    return _write_gzip(path, header, slabs(), fmt)


def _header(fmt: str, size: int, nrrd_type: str, dtype: type, voxel_mm: float) -> bytes:
    """The NRRD header text, or the NIfTI-1 header that starts the gzip data."""
    if fmt == "nrrd":
        return (f"NRRD0004\ntype: {nrrd_type}\ndimension: 3\nsizes: {size} {size} {size}\n"
                f"encoding: gzip\nendian: little\nspace: left-posterior-superior\n"
                f"space directions: ({voxel_mm},0,0) (0,{voxel_mm},0) (0,0,{voxel_mm})\n"
                f"space origin: (0,0,0)\n\n").encode()
    if fmt != "nifti":
        raise ValueError(f"format must be nrrd or nifti, got {fmt!r}")
    import nibabel as nib

    header = nib.Nifti1Header()
    header.set_data_shape((size, size, size))
    header.set_data_dtype(dtype)
    affine = np.diag([voxel_mm, voxel_mm, voxel_mm, 1.0])
    header.set_sform(affine, code=1)
    header.set_qform(affine, code=1)
    header.set_xyzt_units("mm")
    header["vox_offset"] = 352
    return header.binaryblock + b"\0\0\0\0"  # no extensions


def _write_gzip(path: Path, header: bytes, slabs: Iterator[tuple[str, bytes]],
                fmt: str) -> Path:
    """``header`` then gzip of ``slabs`` (NRRD), or gzip of header and slabs (NIfTI). A
    slab with a key already seen reuses its compressed bytes."""
    path = Path(path)
    compressor = zlib.compressobj(6, zlib.DEFLATED, -zlib.MAX_WBITS)
    crc, total = 0, 0
    seen: dict[str, bytes] = {}
    with open(path, "wb") as f:
        if fmt == "nrrd":
            f.write(header)
        f.write(b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\xff")  # gzip, no name, no time
        parts: Iterator[tuple[str, bytes]] = iter(slabs)
        if fmt == "nifti":
            parts = _chain(("", header), parts)
        for key, data in parts:
            crc = zlib.crc32(data, crc)
            total += len(data)
            if key and key in seen:
                f.write(seen[key])
                continue
            out = compressor.compress(data) + compressor.flush(zlib.Z_FULL_FLUSH)
            if key:
                seen[key] = out
            f.write(out)
        f.write(compressor.flush(zlib.Z_FINISH))
        f.write(struct.pack("<II", crc & 0xFFFFFFFF, total & 0xFFFFFFFF))
    return path


def _chain(first: tuple[str, bytes], rest: Iterator[tuple[str, bytes]]
           ) -> Iterator[tuple[str, bytes]]:
    yield first
    yield from rest
