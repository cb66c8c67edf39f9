"""A volume's values a slab at a time: from an array in memory, a file's payload, or a series
of slice files — so a conversion never needs the source whole.

Every source yields blocks: rectangular parts of the volume, in the order its values are stored
(a file's own order), each with the index of the part it is. The converter works on a block
and writes the bone's voxels for it, so a float64 CT of a gigabyte becomes its uint8 bone
through a few tens of megabytes. A source may be read more than once (the values' range first,
then the conversion): a file's payload is then read, and inflated, again.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Protocol

import numpy as np

from .payload import ByteReader

#: Source bytes in one block (at least one row of the fastest axis is read at once). The
#: conversion holds about four times this beside the bone (measured on a 384³ float64 CT: 32
#: MiB slabs took 127 MiB, 8 MiB slabs 35 MiB); a block costs ~0.1 ms of Python.
SLAB_BYTES = 8 << 20

Index = tuple[slice, slice, slice]
Block = tuple[Index, np.ndarray]


class Opener(Protocol):
    """Where a payload is (``payload.Payload``, a .npz member): opened once per pass."""

    def open(self) -> ByteReader: ...


def native(values: np.ndarray) -> np.ndarray:
    """Native byte order and no float16 (the kernels read any of the rest)."""
    if values.dtype == np.float16:
        return values.astype(np.float32)
    if not values.dtype.isnative:
        return values.astype(values.dtype.newbyteorder("="))
    return values


def native_dtype(dtype: np.dtype) -> np.dtype:
    """The dtype :func:`native` gives values of ``dtype``."""
    dtype = np.dtype(dtype)
    if dtype == np.float16:
        return np.dtype(np.float32)
    return dtype if dtype.isnative else dtype.newbyteorder("=")


def block_indices(shape: tuple[int, int, int], fortran: bool,
                  max_elements: int) -> Iterator[Index]:
    """The blocks of a ``shape`` volume stored in C (last axis fastest) or Fortran order, in
    storage order, each contiguous in storage and of at most ``max_elements`` values (a whole
    row of the fastest axis when a row is longer)."""
    order = (0, 1, 2) if fortran else (2, 1, 0)  # fastest first
    fast, mid, slow = order
    n_fast, n_mid, n_slow = shape[fast], shape[mid], shape[slow]
    max_elements = max(int(max_elements), 1)

    def index(f: tuple[int, int], m: tuple[int, int], s: tuple[int, int]) -> Index:
        out = [slice(0, 0)] * 3
        out[fast], out[mid], out[slow] = slice(*f), slice(*m), slice(*s)
        return tuple(out)  # type: ignore[return-value]

    plane = n_fast * n_mid
    if plane <= max_elements:
        step = max(max_elements // plane, 1)
        for s0 in range(0, n_slow, step):
            yield index((0, n_fast), (0, n_mid), (s0, min(s0 + step, n_slow)))
        return
    rows = max(max_elements // n_fast, 1)
    for s in range(n_slow):
        for m0 in range(0, n_mid, rows):
            yield index((0, n_fast), (m0, min(m0 + rows, n_mid)), (s, s + 1))


def block_shape(index: Index) -> tuple[int, int, int]:
    return tuple(s.stop - s.start for s in index)  # type: ignore[return-value]


class VoxelSource:
    """Values of a (nx, ny, nz) volume, block by block.

    Attributes:
        shape: the volume's shape.
        dtype: the values' dtype as blocks come (native byte order; float16 as float32).
        held_bytes: memory the source itself holds while it exists (an array in memory).
    """

    shape: tuple[int, int, int]
    dtype: np.dtype
    held_bytes: int = 0

    def blocks(self) -> Iterator[Block]:
        """(index, values) for every part of the volume once."""
        raise NotImplementedError

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    def array(self) -> np.ndarray:
        """The whole volume in memory, in the widest dtype its blocks come in (for small
        volumes and tests: a load never calls it)."""
        blocks = list(self.blocks())
        dtype = np.result_type(self.dtype, *(b.dtype for _, b in blocks))
        out = np.empty(self.shape, dtype=dtype)
        for index, block in blocks:
            out[index] = block
        return out


class ArraySource(VoxelSource):
    """An array already in memory: blocks are views of it (in its memory order)."""

    def __init__(self, array: np.ndarray) -> None:
        self.array = array
        self.shape = tuple(int(s) for s in array.shape)  # type: ignore[assignment]
        self.dtype = native_dtype(array.dtype)
        self.held_bytes = 0  # already counted where it was made

    def blocks(self) -> Iterator[Block]:
        array = self.array
        fortran = array.flags.f_contiguous and not array.flags.c_contiguous
        per_block = SLAB_BYTES // max(array.dtype.itemsize, 1)
        for index in block_indices(self.shape, fortran, per_block):
            yield index, native(array[index])


class StreamSource(VoxelSource):
    """Values stored in a file's payload (raw or compressed), read a block at a time.

    Args:
        payload: where the bytes are (opened anew for each pass over the blocks).
        shape: the volume's shape.
        dtype: the stored values (with their byte order).
        fortran: the first axis varies fastest (NRRD, NIfTI, a Fortran-ordered .npy).
        transform: applied to each block's values (a NIfTI's scaling), None: as stored.
        out_dtype: the dtype ``transform`` gives.
    """

    def __init__(self, payload: Opener, shape: tuple[int, int, int],
                 dtype: np.dtype, fortran: bool,
                 transform: Callable[[np.ndarray], np.ndarray] | None = None,
                 out_dtype: np.dtype | None = None) -> None:
        self.payload = payload
        self.shape = tuple(int(s) for s in shape)  # type: ignore[assignment]
        self.stored = np.dtype(dtype)
        self.fortran = fortran
        self.transform = transform
        self.dtype = np.dtype(out_dtype) if out_dtype is not None else native_dtype(dtype)

    def blocks(self) -> Iterator[Block]:
        reader = self.payload.open()
        try:
            # Sized by the wider of what is read and what the transform makes of it (a
            # uint8 NIfTI with a scale slope becomes float64).
            per_block = SLAB_BYTES // max(self.stored.itemsize, self.dtype.itemsize, 1)
            order = "F" if self.fortran else "C"
            for index in block_indices(self.shape, self.fortran, per_block):
                shape = block_shape(index)
                values = np.empty(int(np.prod(shape)), dtype=self.stored)
                reader.readinto(memoryview(values).cast("B"))
                block = native(values.reshape(shape, order=order))
                del values
                if self.transform is not None:
                    block = self.transform(block)
                yield index, block
            reader.finish()
        finally:
            reader.close()


class SliceSource(VoxelSource):
    """A volume read one slice (along the last axis) at a time: DICOM files, PNG slices.

    Args:
        read_slice: slice k as an (nx, ny) array.
        shape: the volume's shape.
        dtype: the dtype the slices are taken as (a slice may come wider, e.g. a DICOM
            slice whose HU do not fit int16).
        slice_bytes: the memory one decoded slice takes while it is read.
    """

    def __init__(self, read_slice: Callable[[int], np.ndarray], shape: tuple[int, int, int],
                 dtype: np.dtype, slice_bytes: int = 0) -> None:
        self.read_slice = read_slice
        self.shape = tuple(int(s) for s in shape)  # type: ignore[assignment]
        self.dtype = np.dtype(dtype)
        self.held_bytes = int(slice_bytes)

    def blocks(self) -> Iterator[Block]:
        nx, ny, nz = self.shape
        for k in range(nz):
            values = native(np.asarray(self.read_slice(k)))
            yield (slice(0, nx), slice(0, ny), slice(k, k + 1)), values[:, :, None]


def as_source(data: np.ndarray | VoxelSource) -> VoxelSource:
    return data if isinstance(data, VoxelSource) else ArraySource(np.asarray(data))
