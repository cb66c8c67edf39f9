"""The carve log: what a session's burr removed, as brick records appended to a file.

A record holds the ``swept`` voxels of the bricks that changed since the previous record,
each with the bone version that last changed it. Replayed in order onto the bone its source
loads, the records give back the carved bone (the later record of a brick wins). Only the
bricks that changed are written, so a second of cutting costs a few kB, not the bone.

File format (little-endian), a sequence of records::

    magic  b"BFCR"          4 bytes
    n      uint32           bricks in the record
    length uint32           bytes of the payload that follows
    crc    uint32           CRC-32 of the payload
    payload: index int32[n, 3] (brick coordinates), version int64[n],
             swept uint8[n, 8, 8, 8] (bricks on the grid's far edges padded with 0)

A record cut short by a crash (or failing its CRC) ends the log: everything before it is kept.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..bone.bricks import BRICK
from ..bone.grid import BoneGrid

MAGIC = b"BFCR"
_HEAD = struct.Struct("<4sIII")
BRICK_VOXELS = BRICK ** 3


def brick_records(swept: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The swept voxels of bricks ``index`` (n, 3), as uint8 (n, 8, 8, 8), zero-padded."""
    out = np.zeros((len(index), BRICK, BRICK, BRICK), dtype=np.uint8)
    for n, (a, b, c) in enumerate(index.tolist()):
        block = swept[a * BRICK:(a + 1) * BRICK, b * BRICK:(b + 1) * BRICK,
                      c * BRICK:(c + 1) * BRICK]
        out[n, :block.shape[0], :block.shape[1], :block.shape[2]] = block
    return out


def encode_record(index: np.ndarray, version: np.ndarray, swept: np.ndarray) -> bytes:
    payload = (np.ascontiguousarray(index, dtype="<i4").tobytes()
               + np.ascontiguousarray(version, dtype="<i8").tobytes()
               + np.ascontiguousarray(swept, dtype=np.uint8).tobytes())
    return _HEAD.pack(MAGIC, len(index), len(payload), zlib.crc32(payload)) + payload


def read_log(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The latest record of every brick in the log: (index (n, 3), version (n,), swept
    (n, 8, 8, 8)). A missing file is an empty log."""
    return _scan(path)[:3]


def _scan(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """``read_log`` and the length of the log's valid records, bytes (what follows them is a
    record a crash cut short, or damage)."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        data = b""
    latest: dict[tuple[int, int, int], tuple[int, np.ndarray]] = {}
    at = 0
    while at + _HEAD.size <= len(data):
        magic, n, length, crc = _HEAD.unpack_from(data, at)
        start = at + _HEAD.size
        payload = data[start:start + length]
        if (magic != MAGIC or len(payload) != length
                or length != n * (12 + 8 + BRICK_VOXELS) or zlib.crc32(payload) != crc):
            break  # a record a crash cut short: the log ends before it
        index = np.frombuffer(payload, "<i4", n * 3).reshape(n, 3)
        version = np.frombuffer(payload, "<i8", n, n * 12)
        swept = np.frombuffer(payload, np.uint8, n * BRICK_VOXELS, n * 20).reshape(
            n, BRICK, BRICK, BRICK)
        for i in range(n):
            latest[tuple(index[i].tolist())] = (int(version[i]), swept[i])
        at = start + length
    if not latest:
        return (np.zeros((0, 3), np.int32), np.zeros(0, np.int64),
                np.zeros((0, BRICK, BRICK, BRICK), np.uint8), at)
    keys = list(latest)
    return (np.array(keys, dtype=np.int32), np.array([latest[k][0] for k in keys], np.int64),
            np.stack([latest[k][1] for k in keys]), at)


def apply_log(grid: BoneGrid, index: np.ndarray, version: np.ndarray,
              swept: np.ndarray) -> int:
    """Write the records onto ``grid`` (a freshly loaded bone): its swept voxels, brick
    versions, version and brick summary. Returns the bricks written.

    Raises:
        ValueError: a brick lies outside the grid (the log is for another bone).
    """
    bshape = grid.brick_version.shape
    if len(index) and ((index < 0).any() or (index >= np.array(bshape)).any()):
        raise ValueError(f"the carve log has bricks outside this bone's {bshape} bricks: "
                         "its source changed since it was written")
    for n, (a, b, c) in enumerate(index.tolist()):
        block = grid.swept[a * BRICK:(a + 1) * BRICK, b * BRICK:(b + 1) * BRICK,
                           c * BRICK:(c + 1) * BRICK]
        block[...] = swept[n, :block.shape[0], :block.shape[1], :block.shape[2]]
        grid.brick_version[a, b, c] = version[n]
    if len(index):
        grid.version = max(grid.version, int(version.max()))
        grid.recount()
    return len(index)


class CarveLog:
    """Appends records to one session's log and compacts it when it has grown.

    Args:
        path: the log file.
        since_version: bricks stamped after this version are not in the log yet.
    """

    #: Compact when the file holds this many times the bytes of its latest records.
    COMPACT_RATIO = 4
    COMPACT_MIN_BYTES = 1 << 20

    def __init__(self, path: Path, since_version: int = 0) -> None:
        self.path = path
        self.since_version = since_version
        #: Per brick, whether the log holds it (None until the first append reads the log):
        #: what a compacted log would hold, known without reading it again.
        self._held: np.ndarray | None = None
        #: The highest brick stamp at the previous append (``append`` says why).
        self._last_max = -1

    def reset(self, since_version: int) -> None:
        """A new bone: forget the records (its carving starts at ``since_version``)."""
        self.path.unlink(missing_ok=True)
        self.since_version = since_version
        self._held = None
        self._last_max = -1

    def append(self, swept: np.ndarray, brick_version: np.ndarray) -> int:
        """Write the bricks stamped after ``since_version`` (read from the live, shared
        arrays, without stopping the loop; returns how many).

        The stamps are copied first, then the voxels: a brick the loop rewrites meanwhile
        carries a later stamp and is written again next time. Bricks of the highest stamp
        may belong to a tick still running (a tick stamps with the next version, and ticks
        that remove nothing reuse it), so they are written again at the next append unless
        that stamp was already the highest one then.
        """
        stamps = brick_version.copy()
        top = int(stamps.max()) if stamps.size else 0
        if top <= self.since_version:
            return 0
        if self._held is None:
            self._held = np.zeros(stamps.shape, dtype=bool)
            old, _, _, end = _scan(self.path)
            if len(old) and (old < np.array(stamps.shape)).all():
                self._held[tuple(old.T)] = True
            if self.path.exists() and self.path.stat().st_size > end:
                # A record a crash cut short: appending after it would hide what follows.
                os.truncate(self.path, end)
        index = np.argwhere(stamps > self.since_version)
        versions = stamps[tuple(index.T)]
        record = encode_record(index, versions, brick_records(swept, index))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            start = os.lseek(fd, 0, os.SEEK_END)
            try:
                view = memoryview(record)
                while view:
                    view = view[os.write(fd, view):]
                os.fsync(fd)
            except OSError:
                os.ftruncate(fd, start)  # a full disk: no torn record for the next to follow
                raise
            size = start + len(record)
        finally:
            os.close(fd)
        self.since_version = top if top == self._last_max else top - 1
        self._last_max = top
        self._held[tuple(index.T)] = True
        live = _HEAD.size + int(self._held.sum()) * (12 + 8 + BRICK_VOXELS)
        if size >= self.COMPACT_MIN_BYTES and size > self.COMPACT_RATIO * live:
            write_atomic(self.path, encode_record(*read_log(self.path)))
        return len(index)


def write_atomic(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` so that a crash leaves the old or the new file, never
    a mix (write a temporary file, fsync it, rename it over, fsync the folder)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
