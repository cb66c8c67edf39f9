"""The recording format: a ``NAME.burrrec/`` directory a session's stream is written to.

A recording holds:

- ``meta.json``: what replaying needs besides the rows — format name and version, burrforce
  version, session id and frame, the CuttingParams, ShaftParams and burr resolution, the
  material table, vibration parameters, the bone's name and version at the start, the
  engine's carving state at the start, the wall-clock start time (ISO 8601) and the name of
  the start snapshot;
- ``start.bone.npz``: the bone when recording began (``save_bone``), if there is one;
- ``chunk-000000.npy``, ``chunk-000001.npy``, …: the rows, one per tick, as plain ``.npy``
  files of the structured dtype :data:`ROW_DTYPE` (``np.load`` reads each). A chunk is
  written beside its final name (``.npy.part``) and renamed when whole, so a crash leaves
  every completed chunk readable and at most one ``.part`` file;
- ``summary.json``: written by ``Recorder.close()`` (rows, chunks, rows dropped, why recording
  stopped). Missing, the recorder did not finish (a crash, a kill).

Every field of a row is little-endian and 8-byte aligned (472 bytes a row, ≈ 1.7 GB an hour
at 1 kHz). Vectors of the engine inputs and outputs are in the bone grid's frame (mm, mm/s,
N, N·mm), exactly as ``BoneEngine.step_raw`` took and filled them; ``position``,
``orientation``, ``velocity`` and ``pose_rpm`` are the pose as received (engine frame and
units); ``force`` and ``torque`` are the reply's (engine frame).
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bone.bricks import BRICK
from ..bone.shaft import N_SHAFT
from ..model.kernels import N_OUT
from ..whole_files import WholeFile, write_whole

FORMAT_NAME = "burrforce-recording"
FORMAT_VERSION = 1
SUFFIX = ".burrrec"
META_NAME = "meta.json"
SUMMARY_NAME = "summary.json"
SNAPSHOT_NAME = "start.bone.npz"
PART_SUFFIX = ".part"
CHUNK_RE = re.compile(r"^chunk-(\d{6})\.npy$")
PART_RE = re.compile(r"^chunk-(\d{6})\.npy\.part$")

#: ``rec_flags`` bit: the engine forgot where it last carved just before this tick
#: (``BoneEngine.forget_last_carve``: a stream restart, a teleport, new parameters).
REC_CARVE_RESET = 1
#: Keys ``meta.json`` must hold for a replay.
REQUIRED_META = ("format", "format_version", "params", "shaft", "burr", "materials", "frame")

_FLOATS = (
    ("position", 3), ("orientation", 4), ("velocity", 3), ("pose_rpm", 1),
    ("centre_g", 3), ("axis_g", 3), ("feed_g", 3), ("rpm", 1),
    ("out", N_OUT), ("shaft_out", N_SHAFT), ("removed_mm3", 1), ("force", 3), ("torque", 3),
)

#: One tick. Ints first, then float64s, then the small fields: every field lies on its own
#: natural alignment and no padding is implied (the ``.npy`` header states the layout).
ROW_DTYPE = np.dtype(
    [("t_recv_ns", "<i8"),  # server monotonic clock when the datagram arrived, ns
     ("t_client_us", "<u8"),  # the client's clock, µs
     ("bone_version", "<i8"),  # the bone's version after the tick
     ("seq", "<u4"),  # sequence number
     ("flags", "<u4")]  # the pose's FLAG_* bits
    + [(name, "<f8", (n,)) if n > 1 else (name, "<f8") for name, n in _FLOATS]
    + [("status", "<u2"),  # the reply's STATUS_* bits
       ("spindle_on", "?"),  # the pose's spindle flag
       ("carve", "?"),  # the carve flag passed to step_raw
       ("rec_flags", "u1"),  # REC_* bits
       ("reserved", "u1", (3,))])
#: The same layout for ``struct.pack_into`` (the recorder's hot path).
ROW_STRUCT = struct.Struct(
    f"<qQqII{sum(n for _, n in _FLOATS)}dH??B3x")
assert ROW_STRUCT.size == ROW_DTYPE.itemsize


#: Bricks carved between the start snapshot and the first recorded tick (server recordings).
PATCH_NAME = "start-patch.npz"


class RecordingError(ValueError):
    """A recording that cannot be read: missing, not a recording, or damaged beyond use."""

    def __init__(self, path: Path | str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


def recording_path(path: str | Path) -> Path:
    """``path`` with the ``.burrrec`` suffix (added if missing)."""
    path = Path(path)
    return path if path.name.endswith(SUFFIX) else path.with_name(path.name + SUFFIX)


def chunk_name(index: int) -> str:
    return f"chunk-{index:06d}.npy"


def chunk_header(n_rows: int) -> bytes:
    """The ``.npy`` (format 1.0) header of a chunk of ``n_rows`` rows."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": np.lib.format.dtype_to_descr(ROW_DTYPE), "fortran_order": False,
              "shape": (int(n_rows),)})
    return buf.getvalue()


def write_json(path: Path, value: object) -> None:
    """Write JSON whole or not at all (``whole_files``: a full disk raises ``DiskFull`` and
    leaves nothing)."""
    write_whole(path, json_bytes(value))


def json_bytes(value: object) -> bytes:
    """``value`` as the recording's JSON files hold it (indented, no NaN, a final newline)."""
    return (json.dumps(value, indent=2, allow_nan=False, default=_json_default)
            + "\n").encode("utf-8")


def _json_default(value: object) -> object:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def json_float(x: float) -> float | None:
    """A float for JSON: NaN and infinities become null."""
    return float(x) if math.isfinite(x) else None


# -- reading ---------------------------------------------------------------------------------
@dataclass
class Recording:
    """A recording read back.

    Attributes:
        path: the ``.burrrec`` directory.
        meta: ``meta.json``.
        rows: every readable row, in order (``ROW_DTYPE``).
        snapshot: the start snapshot's path, or None if the recording has none.
        summary: ``summary.json``, or None when the recorder never finished (a crash).
        chunks: chunk files read (a torn one included).
        problems: what was wrong (a torn or missing chunk, a leftover ``.part`` file): the
            rows stop before the first gap, so they are always one unbroken stream.
    """

    path: Path
    meta: dict
    rows: np.ndarray
    snapshot: Path | None
    summary: dict | None
    chunks: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def complete(self) -> bool:
        """Closed by its recorder and nothing torn or missing."""
        return self.summary is not None and not self.problems

    @property
    def stopped_reason(self) -> str | None:
        return None if self.summary is None else self.summary.get("stopped_reason")


def read_recording(path: str | Path) -> Recording:
    """Read a ``.burrrec`` directory: meta, every readable row, the snapshot's path.

    A torn chunk (cut short by a crash or a full disk) keeps its whole rows and is reported
    in ``Recording.problems``; so is a missing chunk, and nothing after a gap is read.

    Raises:
        RecordingError: not a directory, no or unreadable ``meta.json``, another format or
            version, or a chunk of another layout.
    """
    path = Path(path)
    if not path.exists():
        raise RecordingError(path, "no such recording")
    if not path.is_dir():
        raise RecordingError(path, f"not a recording (a recording is a {SUFFIX} directory)")
    meta = _read_json(path, META_NAME, required=True)
    if not isinstance(meta, dict) or meta.get("format") != FORMAT_NAME:
        raise RecordingError(path, f"{META_NAME} is not a burrforce recording's")
    if meta.get("format_version") != FORMAT_VERSION:
        raise RecordingError(path, f"format version {meta.get('format_version')!r} is not "
                                   f"{FORMAT_VERSION}: written by another burrforce")
    missing = [k for k in REQUIRED_META if k not in meta]
    if missing:
        raise RecordingError(path, f"{META_NAME} lacks {', '.join(missing)}")
    summary = _read_json(path, SUMMARY_NAME, required=False)
    if summary is not None and not isinstance(summary, dict):
        summary = None
    snapshot_name = meta.get("snapshot")
    snapshot = None
    if snapshot_name:
        if Path(snapshot_name).name != snapshot_name:
            raise RecordingError(path, f"snapshot {snapshot_name!r} must be a file name")
        snapshot = path / snapshot_name

    chunks: dict[int, Path] = {}
    parts: dict[int, Path] = {}
    for entry in path.iterdir():
        m = CHUNK_RE.match(entry.name)
        if m:
            chunks[int(m.group(1))] = entry
            continue
        m = PART_RE.match(entry.name)
        if m:
            parts[int(m.group(1))] = entry
    problems: list[str] = []
    pieces: list[np.ndarray] = []
    read = 0
    last = max([*chunks, *parts], default=-1)
    for index in range(last + 1):
        file = chunks.get(index)
        if file is None:
            part = parts.get(index)
            if part is not None:
                rows, problem = _read_chunk(path, part)
                read += 1
                pieces.append(rows)
                problems.append(f"{part.name} was being written when recording stopped: "
                                f"{len(rows)} whole rows kept" + (f" ({problem})" if problem
                                                                  else ""))
            else:
                problems.append(f"{chunk_name(index)} is missing")
            if index < last:
                problems.append(f"rows after {chunk_name(index)} are not read (a gap in the "
                                "stream cannot be replayed)")
            break
        rows, problem = _read_chunk(path, file)
        read += 1
        pieces.append(rows)
        if problem is not None:
            problems.append(f"{file.name} is torn: {problem}; {len(rows)} whole rows kept")
            if index < last:
                problems.append(f"rows after {file.name} are not read (a gap in the stream "
                                "cannot be replayed)")
            break
    rows = np.concatenate(pieces) if pieces else np.zeros(0, dtype=ROW_DTYPE)
    if summary is not None and not problems:
        want = summary.get("chunks")
        if isinstance(want, int) and want != read:
            problems.append(f"{SUMMARY_NAME} names {want} chunks, {read} found")
    return Recording(path, meta, rows, snapshot, summary, read, problems)


def _read_json(path: Path, name: str, required: bool) -> object:
    file = path / name
    try:
        with open(file, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        if required:
            raise RecordingError(path, f"no {name}: not a burrforce recording") from None
        return None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        if required:
            raise RecordingError(path, f"{name} is unreadable: {exc}") from None
        return None


def _read_chunk(path: Path, file: Path) -> tuple[np.ndarray, str | None]:
    """(whole rows, problem or None). A chunk of another layout is a RecordingError."""
    try:
        with open(file, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            try:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
                else:
                    return np.zeros(0, ROW_DTYPE), (f"no readable header (.npy version "
                                                    f"{version})")
            except (ValueError, EOFError, SyntaxError) as exc:
                return np.zeros(0, ROW_DTYPE), f"no readable header ({exc})"
            if dtype != ROW_DTYPE or fortran or len(shape) != 1:
                raise RecordingError(path, f"{file.name} is not a chunk of this format "
                                           f"(dtype {dtype}, shape {shape})")
            start = f.tell()
            whole = (size - start) // ROW_DTYPE.itemsize
            n = min(int(shape[0]), whole)
            rows = np.fromfile(f, dtype=ROW_DTYPE, count=n)
    except OSError as exc:
        raise RecordingError(path, f"cannot read {file.name}: {exc}") from None
    if len(rows) < shape[0]:
        return rows, (f"{size - start} bytes of rows where {int(shape[0])} rows need "
                      f"{int(shape[0]) * ROW_DTYPE.itemsize}")
    if size - start > n * ROW_DTYPE.itemsize:
        return rows, f"{size - start - n * ROW_DTYPE.itemsize} bytes after the last row"
    return rows, None


def write_start_patch(folder: Path, grid, since_version: int) -> tuple[int, int]:
    """Save the bricks carved after ``since_version`` (their ``swept`` bytes, zero-padded to
    8³) as ``folder/start-patch.npz``: the start snapshot was taken at ``since_version`` while
    the loop kept cutting. Call it with the loop stopped between two ticks. Returns (bricks
    saved, the bone version they bring the snapshot to)."""
    bricks = np.argwhere(grid.brick_version > since_version)
    swept = np.zeros((len(bricks), BRICK, BRICK, BRICK), dtype=np.uint8)
    for n, (bi, bj, bk) in enumerate(bricks.tolist()):
        block = grid.swept[bi * BRICK:(bi + 1) * BRICK, bj * BRICK:(bj + 1) * BRICK,
                           bk * BRICK:(bk + 1) * BRICK]
        swept[n, :block.shape[0], :block.shape[1], :block.shape[2]] = block
    with WholeFile(Path(folder) / PATCH_NAME) as f:
        np.savez(f, bricks=bricks.astype(np.int32), swept=swept,
                 version=np.int64(grid.version))
    return len(bricks), int(grid.version)


def apply_start_patch(path: Path, grid) -> None:
    """Bring the start snapshot to the bone the first recorded tick carved.

    The server snapshots a session's bone while the loop keeps cutting, then starts the
    recorder between two ticks; the bricks carved in between are saved as
    ``start-patch.npz`` (brick indices, their ``swept`` bytes, 8³ each, and the version)."""
    file = Path(path) / PATCH_NAME
    if not file.is_file():
        return
    try:
        with np.load(file) as z:
            bricks, swept, version = z["bricks"], z["swept"], int(z["version"])
    except (OSError, ValueError, KeyError) as exc:
        raise RecordingError(path, f"the start patch cannot be read: {exc}") from None
    if bricks.ndim != 2 or bricks.shape[1:] != (3,) \
            or swept.shape != (len(bricks), BRICK, BRICK, BRICK):
        raise RecordingError(path, "the start patch has the wrong shape")
    nx, ny, nz = grid.shape
    for (bi, bj, bk), block in zip(bricks.tolist(), swept, strict=True):
        i, j, k = bi * BRICK, bj * BRICK, bk * BRICK
        if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
            raise RecordingError(path, "the start patch does not fit the snapshot")
        target = grid.swept[i:i + BRICK, j:j + BRICK, k:k + BRICK]
        target[...] = block[:target.shape[0], :target.shape[1], :target.shape[2]]
    grid.recount()
    grid.version = version
