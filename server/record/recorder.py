"""Recording a session's stream: one row per tick, written in chunks by a background thread.

The hot loop calls :meth:`Recorder.record` once per tick. It packs the tick into the next row
of a preallocated chunk (one ``struct.pack_into``: 2–4 µs warm) and returns; a full chunk is handed
to the writer thread through a queue and recording continues into a spare chunk. Nothing in
``record`` writes a file, allocates an array or waits: when the writer falls behind (no spare
chunk left) or ``max_bytes`` is reached, recording stops and later ticks are counted as
dropped. When the disk fills up under it, the chunk being written keeps the rows that still
fit, recording stops (``stopped_reason`` says so) and :meth:`Recorder.close` still writes the
summary, in room held for it from the start (``SUMMARY_RESERVE_BYTES``): the recording ends
readable and complete with what it wrote.

Typical use, between two ticks in the loop's thread (the snapshot must be the bone the first
recorded tick carves)::

    recorder = start_recording(session, "run-7", bone_name="temporal")
    ...
    recorder.close()          # any thread
"""

from __future__ import annotations

import collections
import datetime as _dt
import math
import queue
import shutil
import struct
import threading
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ..whole_files import DiskFull, WholeFile, reserve, write_reserved
from .format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    META_NAME,
    PART_SUFFIX,
    PATCH_NAME,
    REC_CARVE_RESET,
    REQUIRED_META,
    ROW_DTYPE,
    ROW_STRUCT,
    SNAPSHOT_NAME,
    SUMMARY_NAME,
    chunk_header,
    chunk_name,
    json_bytes,
    json_float,
    recording_path,
    write_json,
    write_start_patch,
)

if TYPE_CHECKING:
    from ...proto.messages import Pose
    from ..bone.engine import BoneEngine


class Session(Protocol):
    """What a recorder reads of the session it records (the hot loop's ``Session`` is one):
    the room below the hot loop names only what it uses, so it never imports the loop."""

    id: int
    engine: BoneEngine
    #: The session's settings: ``frame``, ``placement_position``/``_orientation``, ``model``,
    #: ``carve``, ``vibration`` (the hot loop's ``SessionConfig``).
    config: Any
    #: The engine frame's transform of the session (the loop's ``EngineTransform``).
    transform: Any
    tool_axis: np.ndarray
    recorder: Recorder | None

DEFAULT_MAX_BYTES = 2 << 30
#: Room held on the disk for ``summary.json`` (about 0.5 kB) from the start, so a recording
#: the disk filled up under still closes complete.
SUMMARY_RESERVE_BYTES = 16 << 10
#: The file that holds it, in the recording's folder (renamed onto the summary at close).
SUMMARY_RESERVE_NAME = ".summary-reserve"
#: Bytes a chunk cut short by a full disk leaves unused, for the file system's rounding to
#: whole blocks.
BLOCK_SLACK_BYTES = 4096
DEFAULT_CHUNK_ROWS = 4096
MAX_CHUNK_ROWS = 1 << 20
#: Chunks in memory: the one being filled plus spares; the writer falls behind when every
#: spare is still waiting to be written (three chunks, ≈ 12 s at 1 kHz with 4096 rows).
N_BUFFERS = 4
_NAN3 = (math.nan, math.nan, math.nan)
_ITEMSIZE = ROW_DTYPE.itemsize


def _now_iso() -> str:
    return _dt.datetime.now(_dt.timezone.utc).astimezone().isoformat(timespec="milliseconds")


def burrforce_version() -> str:
    from .. import __version__

    return __version__


def session_meta(session: Session, bone_name: str = "") -> dict[str, Any]:
    """``meta.json``'s session part: everything besides the rows and the bone that a replay
    needs, taken from ``session`` and its engine now (call it when the snapshot is taken)."""
    engine = session.engine
    config = session.config
    previous = engine.last_carve_g_mm  # the next tick skips what that carve swept
    n_theta, n_phi, refine = engine.burr.key
    return {
        "session_id": session.id,
        "frame": config.frame,
        "tool_axis": [float(x) for x in session.tool_axis],
        "placement_position": [float(x) for x in config.placement_position],
        "placement_orientation": [float(x) for x in config.placement_orientation],
        "model": bool(config.model),
        "carve": bool(config.carve),
        "params": engine.params.to_dict(),
        "shaft": asdict(engine.shaft),
        "burr": {"n_theta": n_theta, "n_phi": n_phi, "refine": refine},
        "materials": [{"label": label, "name": m.name, "us_n_mm2": m.us_n_mm2, "k": m.k,
                       "forbidden": m.forbidden} for label, m in engine.materials],
        "vibration": asdict(config.vibration) if config.vibration is not None else None,
        "bone_name": bone_name,
        "bone_version": int(engine.grid.version),
        "grid_shape": list(engine.grid.shape),
        "spacing_mm": engine.grid.spacing_mm.tolist(),
        "carve_from_g": None if previous is None else [json_float(x) for x in previous],
        "burr_path": engine.path.state(),
        "touching_labels": sorted(engine.touching),
        "engine_ticks": int(engine.ticks),
    }


class Recorder:
    """Writes one session's ticks to a ``.burrrec`` directory (see :mod:`.format`).

    Make one with :meth:`create` (or :func:`start_recording`, which also writes the snapshot
    and attaches it to a session). :meth:`record` is for the loop's thread; :meth:`close` and
    :meth:`status` may be called from any thread.
    """

    def __init__(self, path: Path, max_bytes: int, chunk_rows: int) -> None:
        self.path = path
        self.chunk_rows = chunk_rows
        self.max_bytes = max_bytes
        header = len(chunk_header(chunk_rows))
        per_chunk = header + chunk_rows * _ITEMSIZE
        full, rest = divmod(max_bytes, per_chunk)
        self.max_rows = full * chunk_rows + min(chunk_rows, max(0, rest - header) // _ITEMSIZE)
        self._lock = threading.Lock()
        # Every buffer is touched now, so the hot path never takes a page fault on it.
        self._free: collections.deque = collections.deque()
        for _ in range(N_BUFFERS):
            buf = np.empty(chunk_rows, dtype=ROW_DTYPE)
            raw = buf.view(np.uint8)
            raw.fill(0)
            self._free.append((buf, memoryview(raw)))
        self._buf, self._mv = self._free.popleft()
        self._pack = ROW_STRUCT.pack_into
        self._i = 0  # next row in the current chunk
        self._chunk_index = 0
        self._rows = 0  # rows taken
        self._dropped = 0
        self._rec_flags = 0
        self._active = True
        self._closed = False
        self._stopped_reason: str | None = None
        self._rows_written = 0
        self._chunks_written = 0
        self._bytes_written = 0
        self._write_error: str | None = None
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._session: Session | None = None
        self._engine: BoneEngine | None = None
        self._watch: tuple = ()
        self._hook: tuple | None = None
        self._resets_tracked = False
        self._thread = threading.Thread(target=self._write_loop, name=f"recorder {path.name}",
                                        daemon=True)
        self._thread.start()

    # -- making one ---------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | Path, meta: Mapping[str, Any], snapshot: str | Path | None,
               max_bytes: int = DEFAULT_MAX_BYTES,
               chunk_rows: int = DEFAULT_CHUNK_ROWS) -> Recorder:
        """Start a recording at ``path`` (``.burrrec`` is appended if missing).

        Args:
            path: the recording's directory: created, or an existing one that holds no
                recording yet (the snapshot may already be inside as ``start.bone.npz``).
            meta: ``session_meta(...)`` or the same keys; the format fields, the burrforce
                version, the start time and the snapshot's name are added here.
            snapshot: the bone at the start, a ``.bone.npz`` written with ``save_bone``:
                used in place if it is ``path/start.bone.npz``, else copied there. None: the
                recording has no snapshot (it can be read, not replayed).
            max_bytes: stop recording when the chunk files would grow beyond this.
            chunk_rows: rows per chunk file.

        Raises:
            ValueError: bad arguments, ``meta`` lacks what a replay needs, or ``path`` already
                holds a recording.
            OSError: the directory or the files cannot be written.
        """
        if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes < 0:
            raise ValueError(f"max_bytes must be a non-negative integer, got {max_bytes!r}")
        if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, int) \
                or not 1 <= chunk_rows <= MAX_CHUNK_ROWS:
            raise ValueError(f"chunk_rows must be an integer in 1..{MAX_CHUNK_ROWS}, "
                             f"got {chunk_rows!r}")
        missing = [k for k in REQUIRED_META if k not in meta and k not in
                   ("format", "format_version")]
        if missing:
            raise ValueError(f"recording meta lacks {', '.join(missing)} (see session_meta)")
        path = recording_path(path)
        if path.exists() and not path.is_dir():
            raise ValueError(f"{path} exists and is not a directory")
        if (path / META_NAME).exists() or any(path.glob("chunk-*")):
            raise ValueError(f"{path} already holds a recording")
        path.mkdir(parents=True, exist_ok=True)
        target = path / SNAPSHOT_NAME
        if snapshot is not None:
            snapshot = Path(snapshot)
            if not snapshot.is_file():
                raise ValueError(f"snapshot {snapshot} is not a file")
            if snapshot.resolve() != target.resolve():
                shutil.copyfile(snapshot, target)
        full_meta = {
            **meta,
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "burrforce_version": burrforce_version(),
            "start_time": meta.get("start_time") or _now_iso(),
            "snapshot": SNAPSHOT_NAME if snapshot is not None else None,
            "chunk_rows": chunk_rows,
            "row_bytes": _ITEMSIZE,
        }
        write_json(path / META_NAME, full_meta)
        reserve(path / SUMMARY_RESERVE_NAME, SUMMARY_RESERVE_BYTES)
        return cls(path, max_bytes, chunk_rows)

    # -- the session --------------------------------------------------------------------------
    def attach(self, session: Session) -> None:
        """Record ``session``'s ticks: sets ``session.recorder``, notes every time its engine
        forgets where it last carved (replayed exactly), and stops recording if the engine's
        bone, materials, parameters, shaft or resolution, or the session's frame, change (the
        replay could not follow)."""
        if session.recorder is not None and session.recorder is not self:
            raise ValueError(f"session {session.id} is already being recorded")
        if self._engine is not None:
            raise ValueError("this recorder is already attached")
        engine = session.engine
        original = engine.forget_last_carve

        def forget_last_carve() -> None:
            original()
            with self._lock:
                self._rec_flags |= REC_CARVE_RESET

        engine.forget_last_carve = forget_last_carve  # type: ignore[method-assign]
        self._hook = (engine, original, forget_last_carve)
        self._resets_tracked = True
        self._engine = engine
        self._session = session
        self._watch = (engine.grid, engine.materials, engine.materials.revision,
                       engine.params, engine.shaft, engine.burr, session.transform)
        session.recorder = self

    def detach(self) -> None:
        """Undo :meth:`attach` (``close`` does it)."""
        session, hook = self._session, self._hook
        if hook is not None:
            engine, original, installed = hook
            if engine.__dict__.get("forget_last_carve") is installed:
                if getattr(original, "__self__", None) is engine and getattr(
                        original, "__func__", None) is type(engine).forget_last_carve:
                    del engine.forget_last_carve
                else:
                    engine.forget_last_carve = original
            self._hook = None
        if session is not None and session.recorder is self:
            session.recorder = None
        self._engine = None

    # -- the hot path -------------------------------------------------------------------------
    def record(self, t_recv_ns: int, pose: Pose, centre_g: np.ndarray, axis_g: np.ndarray,
               feed_g: np.ndarray, rpm: float, carve: bool, out: np.ndarray,
               shaft_out: np.ndarray, removed_mm3: float, bone_version: int, status: int,
               force: tuple[float, float, float], torque: tuple[float, float, float]) -> None:
        """One tick, after ``step_raw``: ``centre_g``, ``axis_g``, ``feed_g`` (float64 (3,)
        arrays), ``rpm`` and ``carve`` exactly as passed to it, ``out`` and ``shaft_out`` the
        engine's buffers (copied here), ``force`` and ``torque`` the reply's (engine frame).
        Never raises, never blocks on I/O."""
        with self._lock:
            if not self._active:
                if not self._closed:
                    self._dropped += 1
                return
            engine = self._engine
            if engine is not None:
                w = self._watch
                if (engine.grid is not w[0] or engine.materials is not w[1]
                        or w[1].revision != w[2] or engine.params is not w[3]
                        or engine.shaft is not w[4] or engine.burr is not w[5]
                        or self._session.transform is not w[6]):  # type: ignore[union-attr]
                    self._stop("the bone, materials, parameters, shaft, resolution or frame "
                               "changed: a replay could not follow")
                    self._dropped += 1
                    return
            if self._rows >= self.max_rows:
                self._stop(f"max_bytes ({self.max_bytes} bytes) reached")
                self._dropped += 1
                return
            i = self._i
            velocity = pose.velocity
            try:
                self._pack(
                    self._mv, i * _ITEMSIZE, t_recv_ns, pose.t_client_us, bone_version,
                    pose.seq, pose.flags, *pose.position, *pose.orientation,
                    *(_NAN3 if velocity is None else velocity), pose.rpm,
                    *centre_g.tolist(), *axis_g.tolist(), *feed_g.tolist(), rpm,
                    *out.tolist(), *shaft_out.tolist(), removed_mm3, *force, *torque, status,
                    pose.spindle_on, carve, self._rec_flags)
            except (struct.error, TypeError, ValueError, AttributeError, OverflowError) as exc:
                self._stop(f"a tick could not be recorded: {exc}")
                self._dropped += 1
                return
            self._rec_flags = 0
            self._rows += 1
            i += 1
            if i == self.chunk_rows:
                self._queue.put((self._chunk_index, self._buf, self._mv, i))
                self._chunk_index += 1
                i = 0
                try:
                    self._buf, self._mv = self._free.popleft()
                except IndexError:
                    self._buf = self._mv = None
                    self._stop("the writer fell behind (every spare chunk was still waiting "
                               "to be written)")
            self._i = i

    def _stop(self, reason: str) -> None:
        """Under the lock: record nothing more."""
        self._active = False
        if self._stopped_reason is None:
            self._stopped_reason = reason

    # -- the writer thread --------------------------------------------------------------------
    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            index, buf, mv, n = item
            if self._write_error is None:
                kept, error = self._write_rows(index, mv, n)
                with self._lock:
                    if kept:
                        self._chunks_written += 1
                        self._rows_written += kept
                        self._bytes_written += len(chunk_header(kept)) + kept * _ITEMSIZE
                    if error is not None:
                        self._write_error = error
                        self._stop(error)
            self._free.append((buf, mv))

    def _write_rows(self, index: int, mv: memoryview, n: int) -> tuple[int, str | None]:
        """Write chunk ``index`` (``n`` rows); on a full disk, as many of its rows as still
        fit. Returns (rows kept, why writing stops or None)."""
        try:
            self._write_chunk(index, mv, n)
            return n, None
        except DiskFull as exc:
            free = exc.free_bytes or 0
            fit = min(n - 1, (free - len(chunk_header(n)) - BLOCK_SLACK_BYTES) // _ITEMSIZE)
            kept = 0
            if fit > 0:
                try:
                    self._write_chunk(index, mv, fit)
                    kept = fit
                except OSError:
                    kept = 0
            return kept, (f"the disk is full: {chunk_name(index)} kept {kept} of its {n} "
                          f"rows and recording stopped there ({exc.strerror})")
        except OSError as exc:
            return 0, f"writing {chunk_name(index)} failed: {exc}"

    def _write_chunk(self, index: int, mv: memoryview, n: int) -> None:
        """Beside the final name (``.part``), then renamed: a chunk file is whole, and a
        failed one leaves nothing (``whole_files``)."""
        final = self.path / chunk_name(index)
        with WholeFile(final, part_name=final.name + PART_SUFFIX) as f:
            f.write(chunk_header(n))
            f.write(mv[:n * _ITEMSIZE])  # the GIL is released while the bytes are written

    # -- control ------------------------------------------------------------------------------
    def close(self) -> dict[str, Any]:
        """Stop recording, write what is left and ``summary.json``, detach from the session.
        Blocks until the files are written (not for the loop's thread). Returns
        :meth:`status` (with ``error`` if ``summary.json`` could not be written)."""
        with self._lock:
            if self._closed:
                first = False
            else:
                first = True
                self._closed = True
                self._active = False
                if self._buf is not None and self._i > 0:
                    self._queue.put((self._chunk_index, self._buf, self._mv, self._i))
                    self._chunk_index += 1
                    self._buf = self._mv = None
        if not first:
            self._thread.join()
            return self.status()
        self._queue.put(None)
        self._thread.join()
        self.detach()
        status = self.status()
        summary = {**{k: v for k, v in status.items() if k not in ("path", "closed")},
                   "end_time": _now_iso(), "resets_tracked": self._resets_tracked}
        held = self.path / SUMMARY_RESERVE_NAME
        try:
            if held.is_file():  # the room held for it since the start: a full disk is fine
                write_reserved(held, self.path / SUMMARY_NAME, json_bytes(summary))
            else:
                write_json(self.path / SUMMARY_NAME, summary)
        except OSError as exc:  # the chunks stay readable; the recording reads as unfinished
            status["error"] = f"cannot write {SUMMARY_NAME}: {exc}"
        return status

    def status(self) -> dict[str, Any]:
        """rows (taken), rows_written, dropped, bytes and chunks written, stopped_reason
        (None while recording or after a plain close), closed."""
        with self._lock:
            return {
                "path": str(self.path),
                "rows": self._rows,
                "rows_written": self._rows_written,
                "dropped": self._dropped,
                "bytes": self._bytes_written,
                "chunks": self._chunks_written,
                "stopped_reason": self._stopped_reason,
                "recording": self._active,
                "closed": self._closed,
            }

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_recording(session: Session, path: str | Path, *, bone_name: str = "",
                    max_bytes: int = DEFAULT_MAX_BYTES,
                    chunk_rows: int = DEFAULT_CHUNK_ROWS,
                    snapshot_version: int | None = None) -> Recorder:
    """Start a recording of ``session`` at ``path`` and attach it.

    Call it between ticks in the loop's thread. Without ``snapshot_version`` the bone is
    snapshotted here (compressed: a large bone takes a while). With it, ``path`` already holds
    the start snapshot, taken at that bone version while the loop kept cutting (the server's
    control plane does so from shared memory); only the bricks carved since are saved here,
    as the start patch the replay applies.

    Raises:
        ValueError: ``path`` exists (without ``snapshot_version``), or the session is already
            being recorded.
        OSError: the files cannot be written.
    """
    from ..bone.bone import Bone
    from ..bone.loaders import save_bone

    path = recording_path(path)
    if session.recorder is not None:
        raise ValueError(f"session {session.id} is already being recorded")
    engine = session.engine
    meta = session_meta(session, bone_name)
    if snapshot_version is not None:
        patched, version = write_start_patch(path, engine.grid, snapshot_version)
        meta["start_patch"] = {"file": PATCH_NAME, "bricks": patched,
                               "from_version": int(snapshot_version), "to_version": version}
        recorder = Recorder.create(path, meta, path / SNAPSHOT_NAME, max_bytes=max_bytes,
                                   chunk_rows=chunk_rows)
        recorder.attach(session)
        return recorder
    if path.exists():
        raise ValueError(f"{path} already exists")
    path.mkdir(parents=True)
    try:
        snapshot = save_bone(Bone(engine.grid, engine.materials, name=bone_name,
                                  format="recording", kind="bone"), path / SNAPSHOT_NAME)
        recorder = Recorder.create(path, meta, snapshot, max_bytes=max_bytes,
                                   chunk_rows=chunk_rows)
    except BaseException:
        shutil.rmtree(path, ignore_errors=True)
        raise
    recorder.attach(session)
    return recorder
