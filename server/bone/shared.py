"""A bone both server processes map: the hot loop carves it, the control plane reads it.

The control plane loads a bone (seconds of Python and I/O that must not run in the hot loop's
interpreter), writes its voxels into a file in a run directory (``/dev/shm`` when it is large
enough), and hands the hot loop a :class:`SharedBoneRef`. The hot loop maps the file and builds
its engine on the mapped arrays, so carving writes straight into memory the control plane also
maps. Exports, snapshots and deltas then read the bone without asking the loop for anything.

The file: a header page of int64 counters, then ``density``, ``labels``, ``swept`` (uint8, C
order), ``brick_version`` (int64, brick shape), the brick summary ``brick_bone`` and
``brick_full`` (int32), the brick label mask (uint64, brick shape × 4:
``bricks.brick_labels``) and the carving's tally (``tally``: removal per label, forbidden
contacts), each at a page-aligned offset. The summaries are written by
:func:`publish`, in the process that loaded the bone, so the hot loop builds a session on a
large bone without a pass over its voxels (measured on 512³: 245 ms of kernels that competed
for the two cores with the packet thread).

Only ``swept`` (and the brick counters) change while cutting. The hot loop brackets every
carving tick with a sequence counter (a seqlock: odd while a tick writes), and stamps the bricks
it changes with the new bone version, so a reader copies ``swept`` without stopping the loop and
then re-copies only the few bricks that changed meanwhile (:meth:`SharedBone.consistent_swept`).
The counter is read and written with explicit memory ordering (``seqlock``): plain stores
and loads would let an ARM core see a tick's voxels and its counter out of order.
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
from .bricks import BRICK, LABEL_WORDS, brick_labels, brick_shape
from .grid import BoneGrid
from .materials import Material, MaterialTable
from .seqlock import H_SEQ, H_VERSION, read_begin, read_retry, read_version
from .tally import CarveTally, tally_bytes

T = TypeVar("T")
PAGE = 4096
#: Header slots (int64): H_SEQ and H_VERSION (``seqlock``), then:
H_MAGIC = 2
N_HEADER = 8
MAGIC = 0x6275727266726333  # "burrfrc3": with the brick summaries and the tally
#: Prefer RAM-backed /dev/shm when it has room for the bone plus this margin, bytes.
SHM_MARGIN_BYTES = 64 << 20


def _align(n: int) -> int:
    return (n + PAGE - 1) // PAGE * PAGE


def _layout(shape: tuple[int, int, int]) -> dict[str, int]:
    """Byte offset of each array in the file, and its total ``size``."""
    n = int(np.prod(shape))
    nb = int(np.prod(brick_shape(shape)))
    offsets = {}
    at = PAGE
    for name, nbytes in (("density", n), ("labels", n), ("swept", n),
                         ("brick_version", nb * 8), ("brick_bone", nb * 4),
                         ("brick_full", nb * 4), ("brick_labels", nb * 8 * LABEL_WORDS),
                         ("tally", tally_bytes())):
        offsets[name] = at
        at += _align(nbytes)
    offsets["size"] = at
    return offsets


#: Each array's dtype in the file.
_DTYPES = {"density": np.uint8, "labels": np.uint8, "swept": np.uint8,
           "brick_version": np.int64, "brick_bone": np.int32, "brick_full": np.int32,
           "brick_labels": np.uint64}
#: Bytes handed to one write.
_WRITE_BYTES = 16 << 20


def _write(fd: int, offset: int, array: np.ndarray) -> None:
    """All of ``array``'s bytes (C order) at ``offset`` of the file ``fd``."""
    data = memoryview(np.ascontiguousarray(array)).cast("B")
    done = 0
    while done < len(data):
        done += os.pwrite(fd, data[done:done + _WRITE_BYTES], offset + done)


def _arrays(m: mmap.mmap, shape: tuple[int, int, int]) -> dict[str, np.ndarray]:
    """The file's arrays over the map ``m``."""
    at = _layout(shape)
    n = int(np.prod(shape))
    bshape = brick_shape(shape)
    nb = int(np.prod(bshape))
    return {
        "density": np.frombuffer(m, np.uint8, n, at["density"]).reshape(shape),
        "labels": np.frombuffer(m, np.uint8, n, at["labels"]).reshape(shape),
        "swept": np.frombuffer(m, np.uint8, n, at["swept"]).reshape(shape),
        "brick_version": np.frombuffer(m, np.int64, nb, at["brick_version"]).reshape(bshape),
        "brick_bone": np.frombuffer(m, np.int32, nb, at["brick_bone"]).reshape(bshape),
        "brick_full": np.frombuffer(m, np.int32, nb, at["brick_full"]).reshape(bshape),
        "brick_labels": np.frombuffer(m, np.uint64, nb * LABEL_WORDS,
                                      at["brick_labels"]).reshape((*bshape, LABEL_WORDS)),
    }


#: The file in a run directory naming the process that owns it, written as it is made: a
#: server starting beside it removes only directories whose owner is gone.
OWNER_FILE = "owner.pid"


def run_directory(size_bytes: int = 0) -> Path:
    """A fresh private directory for shared bones: under /dev/shm when it exists and has room
    for ``size_bytes`` (RAM-backed), else the system temporary directory (still shared through
    the page cache, written back to disk lazily). It holds ``OWNER_FILE`` with this process's
    PID from the start."""
    shm = Path("/dev/shm")
    base = None
    if shm.is_dir() and os.access(shm, os.W_OK):
        try:
            if shutil.disk_usage(shm).free > size_bytes + SHM_MARGIN_BYTES:
                base = shm
        except OSError:
            pass
    path = Path(tempfile.mkdtemp(prefix="burrforce-", dir=base))
    (path / OWNER_FILE).write_text(f"{os.getpid()}\n")
    return path


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
        return _layout(self.shape)["size"]


def publish(bone: Bone, directory: Path, name: str,
            tally: CarveTally | None = None) -> SharedBoneRef:
    """Write ``bone``'s voxels (density, labels, swept, brick versions, version), brick
    summaries and ``tally`` (None: zero, a bone nobody cut yet) to a new file
    ``directory/name`` and return the reference the hot loop maps.

    Runs where the bone was loaded (the control plane's loading worker): the brick counts are
    the grid's own, the label mask is one pass over the voxels in a kernel that releases the
    GIL."""
    grid = bone.grid
    size = _layout(grid.shape)["size"]
    path = Path(directory) / name
    with open(path, "xb") as f:
        try:  # reserve the pages now: writing through a map of a full tmpfs is a SIGBUS
            os.posix_fallocate(f.fileno(), 0, size)
        except OSError as exc:
            f.close()
            path.unlink(missing_ok=True)
            raise OSError(exc.errno, f"no room for a {size / 2**20:.0f} MB bone in "
                                     f"{directory}: {exc.strerror}") from None
    # Written, not mapped: pages written through a map count in this process's resident
    # memory until it is unmapped — a second copy of the bone beside the grid it was loaded
    # into. Written, they are only the file's (the hot loop maps them).
    at = _layout(grid.shape)
    labels_mask = grid.brick_labels
    if labels_mask is None:
        labels_mask = np.zeros((*grid.brick_version.shape, LABEL_WORDS), dtype=np.uint64)
        brick_labels(grid.density, grid.labels, labels_mask)
    header = np.zeros(N_HEADER, dtype=np.int64)
    header[H_VERSION] = grid.version
    header[H_MAGIC] = MAGIC
    with open(path, "r+b") as f:
        fd = f.fileno()
        for key, array in (("density", grid.density), ("labels", grid.labels),
                           ("swept", grid.swept), ("brick_version", grid.brick_version),
                           ("brick_bone", grid.brick_bone), ("brick_full", grid.brick_full),
                           ("brick_labels", labels_mask)):
            _write(fd, at[key], array.astype(_DTYPES[key], copy=False))
        if tally is not None:  # small: mapped, only its own pages are touched
            with mmap.mmap(fd, size) as m:
                first, rows = tally.rows_since(0)
                CarveTally.over(m, at["tally"]).load(tally.removed, tally.begun, first, rows)
                m.flush()
        _write(fd, 0, header)
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
        size = _layout(ref.shape)["size"]
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
        arrays = _arrays(m, ref.shape)
        self.density = arrays["density"]
        self.labels = arrays["labels"]
        self.swept = arrays["swept"]
        self.brick_version = arrays["brick_version"]
        #: The brick summary as the hot loop keeps it (it changes as the bone is cut).
        self.brick_bone = arrays["brick_bone"]
        self.brick_full = arrays["brick_full"]
        #: Per brick, a bit per label with bone (``bricks.brick_labels``); never changes.
        self.brick_labels = arrays["brick_labels"]
        #: Removal and forbidden contacts since the bone was loaded (the loop's engine counts
        #: into it: a restarted loop counts on).
        self.tally = CarveTally.over(m, _layout(ref.shape)["tally"])
        self.writable = writable
        self._view: BoneGrid | None = None
        self._view_lock = threading.Lock()

    @property
    def version(self) -> int:
        """The bone version after the last finished carving tick."""
        return int(read_version(self.header))

    def materials(self) -> MaterialTable:
        return MaterialTable({label: Material(name, us, k, forbidden)
                              for label, name, us, k, forbidden in self.ref.materials})

    def bone(self) -> Bone:
        """A Bone whose grid arrays are the mapped memory (the hot loop's engine carves it).

        Writable, the grid takes the file's brick summaries and label mask as they are, not
        scanning the voxels (the hot loop's engine keeps them exact as it cuts)."""
        ref = self.ref
        grid = BoneGrid(self.density, ref.spacing_mm, origin_mm=ref.origin_mm,
                        direction=np.array(ref.direction), labels=self.labels,
                        swept=self.swept, bricks=(self.brick_bone, self.brick_full)
                        if self.writable else None)
        grid.brick_labels = self.brick_labels
        if self.writable:
            grid.brick_version = self.brick_version
            grid.shared_header = self.header
        grid.version = self.version
        return Bone(grid, self.materials(), ref.name, ref.format, ref.kind, list(ref.notes))

    # -- reading while the hot loop carves ----------------------------------------------------
    def _even(self, deadline: float) -> int:
        while True:
            seq = int(read_begin(self.header))
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
        header = self.header
        seq = self._even(deadline)
        since = int(read_version(header))
        out = self.swept.copy()
        version = since
        while read_retry(header, seq):
            seq = self._even(deadline)
            changed = np.argwhere(self.brick_version > since)
            since = version
            version = int(read_version(header))
            for bi, bj, bk in changed:
                sl = (slice(bi * BRICK, bi * BRICK + BRICK), slice(bj * BRICK, bj * BRICK + BRICK),
                      slice(bk * BRICK, bk * BRICK + BRICK))
                out[sl] = self.swept[sl]
        return out, version

    def carving_since(self, since: int, timeout_s: float = 5.0) -> Carving:
        """The bricks stamped after bone version ``since`` (their stamps and voxels) and the
        tally's removal, all as they were at one moment between two carving ticks, without
        stopping the loop: what the journal writes, so that the removal it keeps is exactly
        that of the carving it keeps.

        Copies the bricks once, then re-copies those a tick stamped meanwhile until a pass
        runs between two ticks (as :meth:`consistent_swept`).

        Raises:
            TimeoutError: no quiet moment within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        header = self.header
        shape = self.brick_version.shape
        seq = self._even(deadline)
        stamps = self.brick_version.copy()
        removed = self.tally.removed.copy()
        version = int(read_version(header))
        index = np.argwhere(stamps > since)
        blocks = brick_blocks(self.swept, index)
        while read_retry(header, seq):
            seq = self._even(deadline)
            fresh = self.brick_version.copy()
            removed = self.tally.removed.copy()
            version = int(read_version(header))
            moved = np.argwhere((fresh != stamps) & (fresh > since))
            stamps = fresh
            if len(moved):
                keep = ~np.isin(np.ravel_multi_index(index.T, shape),
                                np.ravel_multi_index(moved.T, shape))
                index = np.concatenate([index[keep], moved])
                blocks = np.concatenate([blocks[keep], brick_blocks(self.swept, moved)])
        return Carving(index, stamps[tuple(index.T)], blocks, removed, version)

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
            self._view.version = int(read_version(self.header))
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


@dataclass(frozen=True)
class Carving:
    """Bricks of a shared bone as :meth:`SharedBone.carving_since` took them.

    Attributes:
        index: brick coordinates, int (n, 3).
        version: each brick's stamp (the bone version that last changed it), int64 (n,).
        blocks: each brick's ``swept`` voxels, uint8 (n, 8, 8, 8) (zero-padded on the
            grid's far edges).
        removed: the tally's removal per label then (``tally``), float64 (256,).
        bone_version: the bone's published version then.
    """

    index: np.ndarray
    version: np.ndarray
    blocks: np.ndarray
    removed: np.ndarray
    bone_version: int


def brick_blocks(swept: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The swept voxels of bricks ``index`` (n, 3), as uint8 (n, 8, 8, 8), zero-padded."""
    out = np.zeros((len(index), BRICK, BRICK, BRICK), dtype=np.uint8)
    for n, (a, b, c) in enumerate(index.tolist()):
        block = swept[a * BRICK:(a + 1) * BRICK, b * BRICK:(b + 1) * BRICK,
                      c * BRICK:(c + 1) * BRICK]
        out[n, :block.shape[0], :block.shape[1], :block.shape[2]] = block
    return out


def end_interrupted_tick(path: str | os.PathLike) -> bool:
    """Close the seqlock a writer left open by dying mid-tick (its sequence counter stays odd
    and readers would wait forever). The half-written tick's bricks are stamped with the next
    version, so the next carving tick publishes them. Only call it once the writer is dead.
    Returns whether the counter was odd."""
    with open(path, "r+b") as f, mmap.mmap(f.fileno(), PAGE) as m:
        header = np.frombuffer(m, np.int64, N_HEADER, 0)
        odd = bool(header[H_SEQ] & 1)
        if odd:
            header[H_SEQ] += 1
        del header
    return odd
