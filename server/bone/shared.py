"""A bone both server processes map: the hot loop carves it, the control plane reads it.

The control plane loads a bone (seconds of Python and I/O that must not run in the hot loop's
interpreter), writes its voxels into a file in a run directory (``/dev/shm`` when it is large
enough), and hands the hot loop a :class:`SharedBoneRef`. The hot loop maps the file and builds
its engine on the mapped arrays, so carving writes straight into memory the control plane also
maps. Exports, snapshots and deltas then read the bone without asking the loop for anything.

The file: a header page of int64 counters, then ``density``, ``labels``, ``swept`` (uint8, C
order) and ``brick_version`` (int64, brick shape), each at a page-aligned offset.

Only ``swept`` (and the brick counters) change while cutting. The hot loop brackets every
carving tick with a sequence counter (a seqlock: odd while a tick writes), and stamps the bricks
it changes with the new bone version, so a reader copies ``swept`` without stopping the loop and
then re-copies only the few bricks that changed meanwhile (:meth:`SharedBone.consistent_swept`).
"""

from __future__ import annotations

import mmap
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from .bone import Bone
from .bricks import BRICK, brick_shape
from .grid import BoneGrid
from .materials import Material, MaterialTable

T = TypeVar("T")
PAGE = 4096
#: Header slots (int64).
H_SEQ = 0  # odd while the hot loop writes voxels
H_VERSION = 1  # the bone version once the last carving tick finished
H_MAGIC = 2
N_HEADER = 8
MAGIC = 0x6275727266726331  # "burrfrc1"
#: Prefer RAM-backed /dev/shm when it has room for the bone plus this margin, bytes.
SHM_MARGIN_BYTES = 64 << 20


def _align(n: int) -> int:
    return (n + PAGE - 1) // PAGE * PAGE


def _layout(shape: tuple[int, int, int]) -> tuple[int, int, int, int, int]:
    """(density, labels, swept, brick_version offsets, total size) in bytes."""
    n = int(np.prod(shape))
    nb = int(np.prod(brick_shape(shape)))
    density = PAGE
    labels = density + _align(n)
    swept = labels + _align(n)
    bricks = swept + _align(n)
    return density, labels, swept, bricks, bricks + _align(nb * 8)


def run_directory(size_bytes: int = 0) -> Path:
    """A fresh private directory for shared bones: under /dev/shm when it exists and has room
    for ``size_bytes`` (RAM-backed), else the system temporary directory (still shared through
    the page cache, written back to disk lazily)."""
    shm = Path("/dev/shm")
    base = None
    if shm.is_dir() and os.access(shm, os.W_OK):
        try:
            if shutil.disk_usage(shm).free > size_bytes + SHM_MARGIN_BYTES:
                base = shm
        except OSError:
            pass
    return Path(tempfile.mkdtemp(prefix="burrforce-", dir=base))


@dataclass(frozen=True)
class SharedBoneRef:
    """Everything a process needs to map a shared bone (picklable, small).

    Attributes:
        path: the mapped file.
        shape: voxels (nx, ny, nz).
        spacing_mm, origin_mm, direction: geometry (as ``BoneGrid``), nested tuples.
        materials: the material table as (label, name, us_n_mm2, k, forbidden) tuples.
        name, format, kind, notes: provenance (as ``Bone``).
    """

    path: str
    shape: tuple[int, int, int]
    spacing_mm: tuple[float, ...]
    origin_mm: tuple[float, ...]
    direction: tuple[tuple[float, ...], ...]
    materials: tuple[tuple[int, str, float, float, bool], ...]
    name: str = ""
    format: str = ""
    kind: str = ""
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def size_bytes(self) -> int:
        return _layout(self.shape)[4]


def publish(bone: Bone, directory: Path, name: str) -> SharedBoneRef:
    """Write ``bone``'s voxels (density, labels, swept, brick versions, version) to a new file
    ``directory/name`` and return the reference the hot loop maps."""
    grid = bone.grid
    d_off, l_off, s_off, b_off, size = _layout(grid.shape)
    path = Path(directory) / name
    with open(path, "xb") as f:
        try:  # reserve the pages now: writing through a map of a full tmpfs is a SIGBUS
            os.posix_fallocate(f.fileno(), 0, size)
        except OSError as exc:
            f.close()
            path.unlink(missing_ok=True)
            raise OSError(exc.errno, f"no room for a {size / 2**20:.0f} MB bone in "
                                     f"{directory}: {exc.strerror}") from None
    with open(path, "r+b") as f, mmap.mmap(f.fileno(), size) as m:
        n = grid.density.size
        np.frombuffer(m, np.uint8, n, d_off)[:] = grid.density.reshape(-1)
        np.frombuffer(m, np.uint8, n, l_off)[:] = grid.labels.reshape(-1)
        np.frombuffer(m, np.uint8, n, s_off)[:] = grid.swept.reshape(-1)
        bv = grid.brick_version
        np.frombuffer(m, np.int64, bv.size, b_off)[:] = bv.reshape(-1)
        header = np.frombuffer(m, np.int64, N_HEADER, 0)
        header[H_VERSION] = grid.version
        header[H_MAGIC] = MAGIC
        del header, bv
        m.flush()
    return SharedBoneRef(
        str(path), tuple(int(x) for x in grid.shape),
        tuple(float(x) for x in grid.spacing_mm), tuple(float(x) for x in grid.origin_mm),
        tuple(tuple(float(x) for x in row) for row in grid.direction),
        tuple((label, m.name, float(m.us_n_mm2), float(m.k), bool(m.forbidden))
              for label, m in bone.materials),
        bone.name, bone.format, bone.kind, tuple(bone.notes))


class SharedBone:
    """A mapped shared bone: a :class:`Bone` over the file's memory.

    Args:
        ref: what :func:`publish` returned.
        writable: the hot loop maps it writable and carves it; readers map it read-only.

    Raises:
        ValueError: the file is missing, of the wrong size, or not a shared bone.
    """

    def __init__(self, ref: SharedBoneRef, writable: bool = False) -> None:
        self.ref = ref
        d_off, l_off, s_off, b_off, size = _layout(ref.shape)
        try:
            with open(ref.path, "r+b" if writable else "rb") as f:
                if os.fstat(f.fileno()).st_size != size:
                    raise ValueError(f"shared bone {ref.path} has the wrong size")
                self._map = mmap.mmap(f.fileno(), size, access=mmap.ACCESS_WRITE
                                      if writable else mmap.ACCESS_READ)
        except FileNotFoundError:
            raise ValueError(f"shared bone {ref.path} does not exist") from None
        m = self._map
        self.header = np.frombuffer(m, np.int64, N_HEADER, 0)
        if int(self.header[H_MAGIC]) != MAGIC:
            raise ValueError(f"{ref.path} is not a shared bone")
        n = int(np.prod(ref.shape))
        self.density = np.frombuffer(m, np.uint8, n, d_off).reshape(ref.shape)
        self.labels = np.frombuffer(m, np.uint8, n, l_off).reshape(ref.shape)
        self.swept = np.frombuffer(m, np.uint8, n, s_off).reshape(ref.shape)
        bshape = brick_shape(ref.shape)
        self.brick_version = np.frombuffer(m, np.int64, int(np.prod(bshape)),
                                           b_off).reshape(bshape)
        self.writable = writable
        self._view: BoneGrid | None = None
        self._view_lock = threading.Lock()

    @property
    def version(self) -> int:
        """The bone version after the last finished carving tick."""
        return int(self.header[H_VERSION])

    def materials(self) -> MaterialTable:
        return MaterialTable({label: Material(name, us, k, forbidden)
                              for label, name, us, k, forbidden in self.ref.materials})

    def bone(self) -> Bone:
        """A Bone whose grid arrays are the mapped memory (the hot loop's engine carves it)."""
        ref = self.ref
        grid = BoneGrid(self.density, ref.spacing_mm, origin_mm=ref.origin_mm,
                        direction=np.array(ref.direction), labels=self.labels,
                        swept=self.swept)
        if self.writable:
            grid.brick_version = self.brick_version
            grid.shared_header = self.header
        grid.version = self.version
        return Bone(grid, self.materials(), ref.name, ref.format, ref.kind, list(ref.notes))

    # -- reading while the hot loop carves ----------------------------------------------------
    def _even(self, deadline: float) -> int:
        while True:
            seq = int(self.header[H_SEQ])
            if not seq & 1:
                return seq
            if time.monotonic() > deadline:
                raise TimeoutError("the hot loop kept the bone busy; try again")
            time.sleep(20e-6)

    def consistent_swept(self, timeout_s: float = 5.0) -> tuple[np.ndarray, int]:
        """(a copy of ``swept``, the bone version it is exact for), without stopping the loop.

        Copies the whole array once, then re-copies the bricks stamped with a later version
        until a pass runs between two carving ticks (a pass copies a few bricks: µs).

        Raises:
            TimeoutError: no quiet moment within ``timeout_s`` (the loop carving nonstop with
                no gap at all, which a 1 kHz stream never does).
        """
        deadline = time.monotonic() + timeout_s
        seq = self._even(deadline)
        since = int(self.header[H_VERSION])
        out = self.swept.copy()
        version = since
        while int(self.header[H_SEQ]) != seq:
            seq = self._even(deadline)
            changed = np.argwhere(self.brick_version > since)
            since = version
            version = int(self.header[H_VERSION])
            for bi, bj, bk in changed:
                sl = (slice(bi * BRICK, bi * BRICK + BRICK), slice(bj * BRICK, bj * BRICK + BRICK),
                      slice(bk * BRICK, bk * BRICK + BRICK))
                out[sl] = self.swept[sl]
        return out, version

    def read_published(self, read: Callable[[BoneGrid], T], timeout_s: float = 5.0) -> T:
        """``read(view)`` on a read-only grid over the mapped voxels whose ``version`` is the
        version published when the read began (between two carving ticks).

        For readers that tolerate later changes: a brick delta sends a brick caught mid-change
        again next time, since its stamp is then newer than that version. Reads through one
        handle run one at a time (they share the view).

        Raises:
            TimeoutError: the loop kept a carving tick open for ``timeout_s``.
        """
        with self._view_lock:
            if self._view is None:
                ref = self.ref
                view = BoneGrid(self.density, ref.spacing_mm, origin_mm=ref.origin_mm,
                                direction=np.array(ref.direction), labels=self.labels,
                                swept=self.swept)
                view.brick_version = self.brick_version
                self._view = view
            self._even(time.monotonic() + timeout_s)
            self._view.version = int(self.header[H_VERSION])
            return read(self._view)

    def snapshot(self, timeout_s: float = 5.0) -> Bone:
        """A private, consistent copy of the bone as it is now (the loop keeps running)."""
        swept, version = self.consistent_swept(timeout_s)
        ref = self.ref
        grid = BoneGrid(self.density.copy(), ref.spacing_mm, origin_mm=ref.origin_mm,
                        direction=np.array(ref.direction), labels=self.labels.copy(),
                        swept=swept)
        grid.brick_version[:] = np.minimum(self.brick_version, version)
        grid.version = version
        return Bone(grid, self.materials(), ref.name, ref.format, ref.kind, list(ref.notes))

    def close(self) -> None:
        """Unmap once no array of it is in use any more."""
        # The arrays stay valid for reads still running (they keep the map alive): only the
        # handle is dropped here.
        try:
            self._map.close()
        except BufferError:  # views still exported (a Bone still alive): the GC unmaps it
            pass
