"""The control plane's state: sessions as the user configured them, bone loads, the hot loops.

The hot loop process owns the live sessions; this side keeps what each session *should* be
(bone source, parameters, features, materials) and sends only the effective settings to the
loop: a feature turned off becomes a setting the loop skips (no shaft: a zero-length shaft; no
vibration: no vibration parameters). Bones are loaded here, in a worker thread, and handed to
the loop through shared memory (``bone.shared``), so a 5-second CT load never runs in the
loop's interpreter, and exports read the bone without asking the loop.

The hot loops are a pool of worker processes (``serve --workers``), each on its own UDP port;
a new session is placed on the least-loaded worker (``place``) and stays there for life.
"""

from __future__ import annotations

import logging
import os
import re
import secrets
import shutil
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ...proto.sequence import seq_after
from ...proto.tag import new_key
from ..bone import Bone, Material, MaterialTable, ShaftParams
from ..bone.engine import check_burr
from ..bone.loaders import BoneFileError, save_bone
from ..bone.shared import (
    SharedBone,
    SharedBoneRef,
    end_interrupted_tick,
    publish,
    run_directory,
)
from ..haptics import PROFILES, DeviceProfile, HapticsConfig
from ..hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec
from ..hotloop.errors import CommandError
from ..hotloop.handle import CALL_TIMEOUT_S, START_TIMEOUT_S
from ..hotloop.pool import start_pool
from ..model.params import CuttingParams
from ..model.shapes import Burr, Sphere
from ..model.vibration import VibrationParams
from .config import ServeConfig
from .generation import bone_generation, next_generation
from .history import TelemetryHistory
from .models import Features, Parameters
from .sources import BoneSource, SourceError, SourceRoots, resolve, snapshot_path
from .telemetry import TelemetryReader

log = logging.getLogger("burrforce.api")

#: Jobs kept for status queries after they finish.
JOBS_KEPT = 200
#: The file in a shared-bone directory naming the process that owns it.
OWNER_FILE = "owner.pid"
RUN_DIR_NAME = re.compile(r"burrforce-[a-z0-9_]{8}")
#: After a restart, stream numbers continue this far past the last one seen (SPEC 5.2): the
#: streams a loop opened after the last look are never offered again.
STREAM_JUMP = 1 << 16
#: Placement compares workers' measured tick work in steps of this, µs of tick per s (1 % of a
#: core): below it, load is noise (an idle session's stray tick) and session count decides.
WORK_STEP_US_PER_S = 10_000.0
#: The HTTP status of each kind of failed hot-loop command (``hotloop.errors``).
COMMAND_STATUS = {"invalid": 422, "not_found": 404, "conflict": 409, "unavailable": 503,
                  "internal": 503}
#: Kinds whose message reaches the caller as the loop said it; the others are prefixed with
#: what failed.
SAID_AS_IS = frozenset({"invalid", "not_found", "conflict"})


class ApiError(Exception):
    """An error the API answers with ``status`` and ``detail``."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


@dataclass
class Job:
    """A bone load (new session, new bone, reset, restore), queryable while it runs."""

    id: str
    kind: str
    session_id: int
    source: str
    state: str = "queued"  # queued | running | done | failed
    error: str | None = None
    stage: str = ""
    done: int = 0
    total: int = 0
    created_s: float = field(default_factory=time.time)
    finished_s: float | None = None
    #: The HTTP status of a failure that is the server's, not the bone's (503: the hot loop
    #: was restarting); None for a bone that could not be loaded.
    status: int | None = None
    #: Set when the job is done or failed.
    finished: threading.Event = field(default_factory=threading.Event, repr=False)

    def public(self) -> dict:
        return {"id": self.id, "kind": self.kind, "session": self.session_id,
                "source": self.source, "state": self.state, "error": self.error,
                "progress": {"stage": self.stage, "done": self.done, "total": self.total},
                "created": self.created_s, "finished": self.finished_s}


@dataclass
class ManagedSession:
    """One session as configured over REST."""

    id: int
    key_hex: str | None
    source: BoneSource
    params: CuttingParams
    shaft: ShaftParams
    vibration: VibrationParams
    config: SessionConfig
    features: Features
    primary_label: int | None = None
    #: The haptic device the force is for (None: no device).
    device: DeviceProfile | None = None
    materials: MaterialTable | None = None
    bone_info: dict | None = None
    ref: SharedBoneRef | None = None
    reader: SharedBone | None = None
    #: An open descriptor of the shared bone file (its name is unlinked once the loop maps
    #: it): what lets a restarted hot loop map the same, carved memory again.
    bone_fd: int | None = None
    state: str = "loading"  # loading | ready | failed
    error: str | None = None
    job_id: str | None = None
    in_loop: bool = False
    #: The index of the hot-loop worker the session runs on, for life (``ControlPlane.place``).
    worker: int = 0
    recording: dict | None = None
    #: The first stream number the next hot loop offers (None: a random one).
    next_stream: int | None = None
    #: Applied once to the next bone loaded, before it is shared: a resumed session's
    #: carving (``journal``).
    pending_carve: Callable[[Bone], None] | None = None
    #: Material changes made over REST, per label (None: the primary material), applied again
    #: to every bone this session loads (a reset keeps the user's Us and K).
    overrides: dict = field(default_factory=dict)
    #: What the hot loop was last sent (params, shaft, config, publish).
    sent: dict = field(default_factory=dict)
    #: Calibrations applied over REST: material label → the latest record.
    calibrations: dict = field(default_factory=dict)
    created_s: float = field(default_factory=time.time)
    #: Serializes changes to this session (loads, parameters, recordings).
    lock: threading.RLock = field(default_factory=threading.RLock)

    def effective_config(self) -> SessionConfig:
        f = self.features
        output = None if f.coupling is None else ("coupled" if f.coupling else "raw")
        return replace(self.config, model=f.model, carve=f.carving,
                       vibration=self.vibration if f.vibration else None,
                       haptics=HapticsConfig.for_device(self.device, output))

    @property
    def output(self) -> str:
        """The output the session renders: raw or coupled."""
        return self.effective_config().haptics.output

    def effective_shaft(self) -> ShaftParams:
        return self.shaft if self.features.shaft else replace(self.shaft, length_mm=0.0)


def _with_burr(params: CuttingParams, p: Parameters) -> CuttingParams:
    """``params`` with ``p``'s burr and radius: a burr replaces the shape (its largest radius
    becomes radius_mm, which must agree if given too); radius_mm alone resizes a round burr.
    ValueError says what does not fit."""
    if p.burr is not None:
        burr = Burr.from_dict(p.burr)
        new = params.with_(burr=burr, radius_mm=burr.shape.max_radius_mm)
        if p.radius_mm is not None and abs(p.radius_mm - new.radius_mm) > 1e-9:
            raise ValueError(f"radius_mm {p.radius_mm} disagrees with the burr's shape (largest "
                             f"radius {new.radius_mm} mm): give the sizes in burr.shape only")
        return new
    if p.radius_mm is None:
        return params
    shape = params.shape
    if abs(p.radius_mm - params.radius_mm) <= 1e-9:
        return params  # re-sent as it is (any shape)
    if not isinstance(shape.shape, Sphere):
        raise ValueError(f"radius_mm resizes a round burr; this one is a {shape.shape.kind}: "
                         f"give its sizes in burr.shape")
    return params.with_(burr=Burr(Sphere(p.radius_mm), shape.cutter), radius_mm=p.radius_mm)


def _device(current: DeviceProfile | None, p: Parameters) -> DeviceProfile | None:
    """The device profile after ``p`` (parameters.device and device_limits)."""
    limits = {} if p.device_limits is None else p.device_limits.model_dump(exclude_none=True)
    name = p.device
    if name is None and not limits:
        return current
    if name == "none":
        if limits:
            raise ValueError("device_limits need a device profile, not none")
        return None
    if name is None or name == "custom":
        base = current if current is not None else PROFILES["generic"]
        if name == "custom" and not limits and current is None:
            raise ValueError("a custom device needs device_limits")
        return base.customized(**limits) if limits else base
    return PROFILES[name].customized(**limits) if limits else PROFILES[name]


class ControlPlane:
    """Sessions, loads and the hot loops behind the REST API. Thread-safe.

    Args:
        config: the server configuration.
        hot: a started hot loop, or the started pool of them (worker i at index i; the caller
            owns starting and stopping them).
    """

    def __init__(self, config: ServeConfig,
                 hot: HotLoopProcess | Sequence[HotLoopProcess]) -> None:
        self.config = config
        #: The hot-loop workers; the supervisor replaces one in place when it restarts it.
        self.workers: list[HotLoopProcess] = ([hot] if isinstance(hot, HotLoopProcess)
                                              else list(hot))
        if not self.workers:
            raise ValueError("a control plane needs at least one hot loop")
        #: Per session id, measured tick work, µs per s (``LoopStats.work_us_per_s``); set by
        #: whoever polls the loops' statistics. None: placement counts sessions only.
        self.work_us_per_s: Callable[[], dict[int, float]] | None = None
        self.started_s = time.time()
        self.data_dir = Path(config.data_dir).expanduser()
        self.roots = SourceRoots(config.bone_library, self.data_dir / "uploads",
                                 self.data_dir / "snapshots")
        for d in (self.roots.uploads, self.roots.snapshots, self.data_dir / "recordings",
                  self.data_dir / "exports"):
            d.mkdir(parents=True, exist_ok=True)
        self.recordings_dir = self.data_dir / "recordings"
        self.run_dir = run_directory(0)
        (self.run_dir / OWNER_FILE).write_text(f"{os.getpid()}\n")
        remove_stale_run_directories(self.run_dir.parent, keep=self.run_dir)
        #: Each session's live state, mapped from the hot loop (``telemetry``).
        self.telemetry = TelemetryReader(self.run_dir)
        #: Each ready session's telemetry sampled at 100 Hz, for its live report (``history``).
        self.history = TelemetryHistory(self, self.telemetry)
        self.sessions: dict[int, ManagedSession] = {}
        self.jobs: dict[str, Job] = {}
        self._lock = threading.RLock()
        self._loads = ThreadPoolExecutor(max_workers=1, thread_name_prefix="burrforce-load")
        self._file_counter = 0
        from .devices import DeviceAttachments  # (it imports this module)

        #: Local haptic devices driven from sessions (``routes_devices``).
        self.devices = DeviceAttachments()
        self.history.start()

    # -- workers ------------------------------------------------------------------------------
    @property
    def hot(self) -> HotLoopProcess:
        """Worker 0 (the only one with ``--workers 1``)."""
        return self.workers[0]

    @hot.setter
    def hot(self, hot: HotLoopProcess) -> None:
        self.workers[0] = hot

    def worker(self, session: ManagedSession) -> HotLoopProcess:
        """The hot loop ``session`` runs on."""
        return self.workers[session.worker]

    def address(self, session: ManagedSession) -> tuple[str, int] | None:
        """The UDP endpoint of ``session``'s worker (None before it first started)."""
        return self.workers[session.worker].address

    def place(self) -> int:
        """The worker a new session goes to: of the running ones (a dead worker's last
        statistics would make it look idle), the least measured tick work of its sessions
        (``WORK_STEP_US_PER_S`` steps), then the fewest sessions, then the lowest index.
        Call with ``_lock`` held (the sessions must not change meanwhile)."""
        n = len(self.workers)
        if n == 1:
            return 0
        alive = [i for i in range(n) if self.workers[i].is_alive()] or list(range(n))
        measured = self.work_us_per_s() if self.work_us_per_s is not None else {}
        work = [0.0] * n
        count = [0] * n
        for s in self.sessions.values():
            if 0 <= s.worker < n:
                count[s.worker] += 1
                work[s.worker] += measured.get(s.id, 0.0)
        return min(alive, key=lambda i: (int(work[i] // WORK_STEP_US_PER_S), count[i], i))

    def worker_sessions(self, index: int) -> list[int]:
        """The ids of the sessions placed on worker ``index``."""
        with self._lock:
            return sorted(s.id for s in self.sessions.values() if s.worker == index)

    # -- sessions -----------------------------------------------------------------------------
    def create_session(self, session_id: int | None, bone: BoneSource, params: Parameters,
                       features: Features, authenticated: bool = True,
                       key_hex: str | None = None,
                       prepare: Callable[[ManagedSession], None] | None = None,
                       worker: int | None = None) -> tuple[ManagedSession, Job]:
        """Register a session and start loading its bone (``Job``). The session reaches the
        hot loop when the load finishes. ``prepare`` sets what a resumed session had
        (material changes, its carving) before the load starts; ``worker`` is the one it
        ran on (its engine streams to that port), kept if the pool still has it, else the
        session is placed (``place``)."""
        base = ManagedSession(0, None, bone, CuttingParams(), ShaftParams(), VibrationParams(),
                              SessionConfig(), features)
        self._apply_parameters(base, params, check_bone=False)
        if prepare is not None:
            prepare(base)
        with self._lock:
            if len(self.sessions) >= self.config.max_sessions:
                raise ApiError(429, f"the server holds its maximum of "
                                    f"{self.config.max_sessions} sessions (max_sessions): "
                                    "delete one first")
            if session_id is None:
                session_id = next(i for i in range(1, 1 << 32) if i not in self.sessions)
            elif session_id in self.sessions:
                raise ApiError(409, f"session {session_id} exists")
            if key_hex is None and authenticated:
                key_hex = new_key().hex()
            base.id = session_id
            base.key_hex = key_hex if authenticated else None
            base.worker = (worker if worker is not None and 0 <= worker < len(self.workers)
                           else self.place())
            self.sessions[session_id] = base
            job = self._submit(base, "create", bone)
        return base, job

    @staticmethod
    def wait(job: Job, timeout_s: float = 600.0) -> bool:
        """Wait until ``job`` is done or failed (True) or ``timeout_s`` passes (False)."""
        return job.finished.wait(timeout_s)

    def get(self, session_id: int) -> ManagedSession:
        with self._lock:
            session = self.sessions.get(session_id)
        if session is None:
            raise ApiError(404, f"no session {session_id}")
        return session

    def ready(self, session_id: int) -> ManagedSession:
        session = self.get(session_id)
        if session.state != "ready":
            raise ApiError(409, f"session {session_id} is {session.state}"
                           + (f": {session.error}" if session.error else "")
                           + (f" (job {session.job_id})" if session.state == "loading" else ""))
        return session

    def delete_session(self, session_id: int) -> None:
        session = self.get(session_id)
        self.devices.discard(session_id)  # its device is zeroed before the session goes
        with session.lock:
            self._stop_recording(session)
            with self._lock:
                self.sessions.pop(session_id, None)
                # Now, before a new session may take the id: it must get a file of its own
                # (the old loop keeps writing its map of the unlinked one until removed).
                self.telemetry.discard(session_id)
                self.history.drop(session_id)
            # Now, not at the journal's next pass: a stop meanwhile must not resume it.
            shutil.rmtree(journal_dir(self.data_dir) / str(session_id), ignore_errors=True)
            try:
                if session.in_loop:
                    session.in_loop = False
                    self.call("remove_session", worker=session.worker,
                              session_id=session_id)
            except ApiError as exc:  # a dead loop has no session left to remove
                log.warning("removing session %s from the hot loop: %s", session_id,
                            exc.detail)
            finally:
                self._drop_bone(session)

    def load_bone(self, session_id: int, bone: BoneSource, kind: str = "load") -> Job:
        """Replace a session's bone (a new source, a reset or a restore)."""
        session = self.get(session_id)
        with session.lock:
            job = self.jobs.get(session.job_id or "")
            if job is not None and job.state in ("queued", "running"):
                raise ApiError(409, f"session {session_id} is already loading a bone (job "
                                    f"{job.id})")
            return self._submit(session, kind, bone)

    def reset(self, session_id: int) -> Job:
        """The bone as its source gives it (uncarved), and a new stream."""
        session = self.get(session_id)
        return self.load_bone(session_id, session.source, "reset")

    def restart_stream(self, session_id: int) -> None:
        self.ready(session_id)
        self.call("restart_stream", session_id=session_id)

    # -- loading ------------------------------------------------------------------------------
    def _submit(self, session: ManagedSession, kind: str, bone: BoneSource) -> Job:
        job = Job(secrets.token_hex(8), kind, session.id, bone.source)
        with self._lock:
            self.jobs[job.id] = job
            while len(self.jobs) > JOBS_KEPT:
                oldest = next(iter(self.jobs))
                if self.jobs[oldest].state in ("queued", "running"):
                    break
                del self.jobs[oldest]
        # A running session stays ready (cut, exported) on its old bone until the swap.
        if not session.in_loop:
            session.state, session.error = "loading", None
        session.job_id = job.id
        self._loads.submit(self._run_load, session, job, bone)
        return job

    def _run_load(self, session: ManagedSession, job: Job, source: BoneSource) -> None:
        job.state = "running"

        def progress(stage: str, done: int, total: int) -> None:
            job.stage, job.done, job.total = stage, int(done), int(total)

        try:
            job.stage = "reading"
            bone = source.load(progress)
            job.stage = "checking"
            self._check_bone(session, bone)
            carve, session.pending_carve = session.pending_carve, None
            if carve is not None:
                job.stage = "replaying the journal"
                carve(bone)
            job.stage = "sharing"
            with self._lock:
                self._file_counter += 1
                name = f"session-{session.id}-{self._file_counter}.bone"
            ref = publish(bone, self.run_dir, name)
            del bone
            job.stage = "starting"
            with session.lock:
                if self.sessions.get(session.id) is not session:
                    Path(ref.path).unlink(missing_ok=True)
                    raise ApiError(410, "the session was deleted while its bone loaded")
                self._stop_recording(session)
                reader = SharedBone(ref)
                materials = reader.materials()
                primary = session.primary_label
                if primary is None or primary not in materials:
                    primary = default_primary(materials)
                if None in session.overrides and primary is not None:
                    overrides = dict(session.overrides)
                    overrides[primary] = {**overrides.pop(None), **overrides.get(primary, {})}
                    session.overrides = overrides
                try:
                    materials = with_overrides(materials, primary, session.overrides)
                except ValueError as exc:
                    reader.close()
                    Path(ref.path).unlink(missing_ok=True)
                    raise ApiError(422, str(exc)) from None
                spec = self._spec(session, ref, materials)
                try:
                    info = self.call("replace_session" if session.in_loop
                                     else "add_session", spec=spec)
                except ApiError:
                    reader.close()
                    Path(ref.path).unlink(missing_ok=True)
                    raise
                # Both processes map it now: the name can go, so no crash leaves it behind;
                # the descriptor keeps the memory reachable for a restarted loop.
                fd = os.open(ref.path, os.O_RDWR)
                Path(ref.path).unlink(missing_ok=True)
                session.sent = {"params": spec.params, "shaft": spec.shaft,
                                "config": spec.config, "publish": spec.publish}
                old = (session.reader, session.ref, session.bone_fd)
                session.in_loop = True
                session.ref, session.reader, session.bone_fd = ref, reader, fd
                session.materials, session.primary_label = materials, primary
                session.source = source
                # After session.reader, never before: generation.py's "Reading order".
                session.bone_info = {**_bone_summary(reader, info),
                                     "generation": next_generation(self.data_dir)}
                session.state, session.error = "ready", None
                self._close_bone(*old)
            job.state = "done"
        except ApiError as exc:
            self._fail(session, job, exc.detail, exc.status if exc.status == 503 else None)
        except (BoneFileError, SourceError, ValueError, OSError, RuntimeError) as exc:
            self._fail(session, job, str(exc))
        except MemoryError:
            self._fail(session, job, "not enough memory to load the bone")
        except Exception as exc:  # the worker must survive anything a loader throws
            log.exception("loading %s failed", source.source)
            self._fail(session, job, f"{type(exc).__name__}: {exc}")
        finally:
            job.finished_s = time.time()
            job.finished.set()

    def _fail(self, session: ManagedSession, job: Job, message: str,
              status: int | None = None) -> None:
        job.state, job.error = "failed", message
        job.status = status
        # A session that already runs keeps its bone; a new one is marked failed.
        if session.in_loop:
            session.state, session.error = "ready", None
        else:
            session.state, session.error = "failed", message

    def _check_bone(self, session: ManagedSession, bone: Bone) -> None:
        try:
            check_burr(bone.grid.spacing_mm, session.params, session.shaft)
        except ValueError as exc:
            raise ApiError(422, str(exc)) from None

    def _spec(self, session: ManagedSession, ref: SharedBoneRef,
              materials: MaterialTable) -> SessionSpec:
        key = bytes.fromhex(session.key_hex) if session.key_hex else None
        return SessionSpec(session.id, ref, None, key, session.effective_config(),
                           session.params, session.effective_shaft(),
                           materials=materials, publish=session.features.deltas,
                           next_stream=session.next_stream,
                           telemetry=self.telemetry.path(session.id))

    # -- a restarted hot loop -----------------------------------------------------------------
    def rebuild(self, hot: HotLoopProcess, streams: dict[int, int] | None = None,
                worker: int = 0) -> list[str]:
        """Make ``hot`` (a new, running loop) worker ``worker`` and move every session the
        old one ran into it (the other workers' sessions are not touched): same id,
        key, parameters and materials, and the carved bone itself: the new loop maps the
        same memory again, through the descriptor kept since the load.

        ``streams`` (session id → the next stream number the old loop last reported) makes
        the new loop hand out stream numbers past any the old one may have opened since
        (``STREAM_JUMP``), so nothing captured from before the crash is accepted again.

        Returns a line for each thing the crash ended (a recording, a session that could not
        be rebuilt)."""
        self.workers[worker] = hot
        notes = []
        for session in list(self.sessions.values()):
            if session.worker != worker:
                continue
            with session.lock:
                if not session.in_loop or session.bone_fd is None or session.ref is None:
                    continue
                if session.recording is not None:
                    notes.append(f"session {session.id}: recording {session.recording['name']}"
                                 " ended with the loop (kept up to its last chunk)")
                    session.recording = None
                # Always forward, from the later of what the loop last reported and what it
                # was started with: a second crash before the next report must not offer the
                # numbers the first restart did.
                base = later_stream((streams or {}).get(session.id), session.next_stream)
                if base is not None:
                    session.next_stream = next_stream_after(base)
                path = f"/proc/{os.getpid()}/fd/{session.bone_fd}"
                end_interrupted_tick(path)
                spec = self._spec(session, replace(session.ref, path=path), session.materials)
                try:
                    self.call("add_session", spec=spec)
                except ApiError as exc:
                    if exc.status == 503:  # the new loop died too: the next restart retries
                        notes.append(f"session {session.id}: not rebuilt yet ({exc.detail})")
                        continue
                    session.in_loop = False
                    session.state, session.error = "failed", (
                        f"not rebuilt after the hot loop restarted: {exc.detail}")
                    notes.append(f"session {session.id}: {session.error}")
                    continue
                session.sent = {"params": spec.params, "shaft": spec.shaft,
                                "config": spec.config, "publish": spec.publish}
        return notes

    def _drop_bone(self, session: ManagedSession) -> None:
        self._close_bone(session.reader, session.ref, session.bone_fd)
        session.reader = session.ref = session.bone_fd = None

    @staticmethod
    def _close_bone(reader: SharedBone | None, ref: SharedBoneRef | None,
                    fd: int | None = None) -> None:
        if reader is not None:
            reader.close()
        if fd is not None:
            os.close(fd)
        if ref is not None:
            # The loop may still map it until its old engine is collected: unlinking only
            # removes the name; the memory goes with the last mapping.
            Path(ref.path).unlink(missing_ok=True)

    # -- parameters ---------------------------------------------------------------------------
    def update_parameters(self, session_id: int, params: Parameters) -> ManagedSession:
        session = self.get(session_id)
        changed = [k for k in ("frame", "placement_position", "placement_orientation")
                   if getattr(params, k) is not None
                   and getattr(params, k) != getattr(session.config, k)]
        if changed and self.devices.attached(session_id):
            # The device loop converts its poses with the frame and placement it started
            # with: changing them under it would misplace the burr and misread k and b.
            raise ApiError(409, f"session {session_id} drives a device: detach it (DELETE "
                                f"…/device) before changing {', '.join(changed)}")
        with session.lock:
            self._apply_parameters(session, params, check_bone=True)
        return session

    def _apply_parameters(self, session: ManagedSession, p: Parameters,
                          check_bone: bool) -> None:
        """Validate everything first, then change the session, then the loop (all or
        nothing: a bad field leaves the session as it was)."""
        try:
            params = session.params.with_(**{k: v for k, v in (
                ("spin", p.spin), ("min_cutting_rpm", p.min_cutting_rpm)) if v is not None})
            params = _with_burr(params, p)
            shaft = replace(session.shaft, **{k: v for k, v in (
                ("radius_mm", p.shaft_radius_mm), ("length_mm", p.shaft_length_mm),
                ("stiffness_n_mm3", p.shaft_stiffness_n_mm3)) if v is not None})
            harmonic = p.harmonic
            if harmonic is None and params.shape.cutter != session.params.shape.cutter:
                harmonic = params.shape.cutter.harmonic  # flutes set the tooth frequency
            vibration = replace(session.vibration, **{k: v for k, v in (
                ("fd_N", p.fd_N), ("g", p.g), ("harmonic", harmonic)) if v is not None})
            config = replace(session.config, **{k: v for k, v in (
                ("frame", p.frame), ("tool_axis", p.tool_axis),
                ("placement_position", p.placement_position),
                ("placement_orientation", p.placement_orientation)) if v is not None})
            device = _device(session.device, p)
        except (TypeError, ValueError) as exc:
            raise ApiError(422, str(exc)) from None
        # The bone's voxels are checked once one is loaded (_check_bone for a new one).
        spacing = session.ref.spacing_mm if check_bone and session.ref is not None else (0.0,)
        try:
            check_burr(spacing, params, shaft)
        except ValueError as exc:
            raise ApiError(422, str(exc)) from None
        materials = session.materials
        primary = session.primary_label
        if p.primary_material is not None:
            if materials is not None and p.primary_material not in materials:
                raise ApiError(422, f"the bone has no material with label "
                                    f"{p.primary_material}")
            primary = p.primary_material
        overrides = dict(session.overrides)
        us_k = {k: v for k, v in (("us_n_mm2", p.us_n_mm2), ("k", p.k)) if v is not None}
        if us_k:
            target = primary if materials is not None else None  # None: the primary, on load
            if materials is not None and primary is None:
                raise ApiError(422, "the bone has no cuttable material to set Us/K on")
            overrides[target] = {**overrides.get(target, {}), **us_k}
            if materials is not None:
                try:
                    materials = with_overrides(materials, primary, {target: us_k})
                except ValueError as exc:
                    raise ApiError(422, str(exc)) from None
        old = (session.params, session.shaft, session.vibration, session.config,
               session.materials, session.primary_label, session.overrides, session.device)
        session.params, session.shaft, session.vibration, session.config = (
            params, shaft, vibration, config)
        session.device = device
        session.materials, session.primary_label = materials, primary
        session.overrides = overrides
        try:
            self._push(session, materials=materials is not old[4])
        except Exception:
            (session.params, session.shaft, session.vibration, session.config,
             session.materials, session.primary_label, session.overrides,
             session.device) = old
            raise

    def update_features(self, session_id: int, features: Features) -> ManagedSession:
        session = self.get(session_id)
        with session.lock:
            old = session.features
            session.features = features
            try:
                self._push(session)
            except Exception:
                session.features = old
                raise
        return session

    def set_material(self, session_id: int, label: int, material: Material | None,
                     changes: dict | None = None) -> ManagedSession:
        session = self.ready(session_id)
        with session.lock:
            assert session.materials is not None
            table = session.materials.copy()
            try:
                if material is not None:
                    table.set(label, material)
                elif label not in table:
                    raise ApiError(404, f"no material with label {label}")
                else:
                    table.update(label, **(changes or {}))
            except (KeyError, ValueError) as exc:
                raise ApiError(422, str(exc.args[0]) if exc.args else str(exc)) from None
            old = session.materials, session.overrides
            m = table[label]
            session.materials = table
            session.overrides = {**session.overrides, label: {
                "name": m.name, "us_n_mm2": m.us_n_mm2, "k": m.k, "forbidden": m.forbidden}}
            try:
                self._push(session, materials=True)
            except Exception:
                session.materials, session.overrides = old
                raise
        return session

    def calibration_target(self, session_id: int, label: int | None) -> tuple[int, Material]:
        """The material a calibration would set: ``label``, default the primary."""
        session = self.ready(session_id)
        label = session.primary_label if label is None else label
        if label is None:
            raise ApiError(422, "the session's bone has no primary material: give label")
        assert session.materials is not None
        if label not in session.materials:
            raise ApiError(404, f"no material with label {label}")
        return label, session.materials[label]

    def apply_calibration(self, session_id: int, label: int, us_n_mm2: float,
                          k: float | None, fit: dict | None, provenance: dict | None) -> dict:
        """Set material ``label``'s Us and K (None: keep its K) and keep a record of it with
        the fit's summary (``fit``) or the caller's ``provenance``."""
        session = self.ready(session_id)
        with session.lock:  # re-entrant: set_material takes it too
            assert session.materials is not None
            before = session.materials[label]
            k = before.k if k is None else k
            if not 0.0 <= k <= 100.0:
                raise ApiError(422, f"the fitted K = {k:.4g} is outside [0, 100], which the "
                                    "model cannot take: fit Us alone with K fixed")
            self.set_material(session_id, label, None, {"us_n_mm2": us_n_mm2, "k": k})
            after = session.materials[label]
            record = {
                "label": label, "material": after.name, "us_n_mm2": after.us_n_mm2,
                "k": after.k, "previous": {"us_n_mm2": before.us_n_mm2, "k": before.k},
                "fit": fit, "provenance": provenance, "applied_s": time.time(),
            }
            session.calibrations = {**session.calibrations, label: record}
        return {"label": label, "material": asdict(after), "calibration": record}

    def _push(self, session: ManagedSession, materials: bool = False) -> None:
        """Send the loop what differs from what it has (if the session runs there): a Us
        change does not restart the stream, a frame change does."""
        if not session.in_loop:
            return
        sent = session.sent
        kwargs: dict = {}
        if session.params != sent.get("params"):
            kwargs["params"] = session.params
        if session.effective_shaft() != sent.get("shaft"):
            kwargs["shaft"] = session.effective_shaft()
        if materials:
            kwargs["materials"] = session.materials.copy()
        if session.features.deltas != sent.get("publish"):
            kwargs["publish"] = session.features.deltas
        config = session.effective_config()
        if kwargs:
            self.call("set_engine", session_id=session.id, **kwargs)
            sent.update({k: v for k, v in kwargs.items() if k != "materials"})
        if config != sent.get("config"):
            self.call("configure", session_id=session.id, config=config)
            sent["config"] = config

    def call(self, command: str, worker: int | None = None, **kwargs: object) -> object:
        """A hot-loop command, its failures as API errors by their kind (``COMMAND_STATUS``):
        bad arguments → 422, a missing session → 404, a session id in use → 409, a dead loop
        or anything else → 503. It goes to ``worker``,
        default the worker of the session it names (``session_id`` or ``spec``)."""
        if worker is None:
            spec = kwargs.get("spec")
            sid = kwargs.get("session_id", getattr(spec, "session_id", None))
            with self._lock:
                session = self.sessions.get(sid)  # type: ignore[arg-type]
            worker = session.worker if session is not None else 0
        # Adding a session maps and warms its bone (a first start may compile kernels).
        timeout_s = (START_TIMEOUT_S if command in ("add_session", "replace_session")
                     else CALL_TIMEOUT_S)
        try:
            return self.workers[worker].call(command, timeout_s=timeout_s, **kwargs)
        except CommandError as exc:
            raise ApiError(COMMAND_STATUS[exc.kind], exc.message if exc.kind in SAID_AS_IS
                           else f"the hot loop cannot do it: {exc.message}") from None

    # -- reading the bone ---------------------------------------------------------------------
    def snapshot_bone(self, session_id: int) -> Bone:
        """A consistent private copy of the session's bone as it is now."""
        session = self.ready(session_id)
        if not session.features.deltas:
            raise ApiError(409, "the session has deltas off: the loop does not publish the "
                                "bone while it is cut; turn the feature on first")
        reader = session.reader
        assert reader is not None
        try:
            bone = reader.snapshot()
        except TimeoutError as exc:
            raise ApiError(503, str(exc)) from None
        bone.materials = session.materials.copy() if session.materials else bone.materials
        return bone

    def save_snapshot(self, session_id: int, name: str | None) -> dict:
        generation = bone_generation(self.get(session_id))  # before the bone: generation.py
        bone = self.snapshot_bone(session_id)
        if name is None:
            name = f"session-{session_id}-v{bone.grid.version}-{time.strftime('%Y%m%d-%H%M%S')}"
        path = snapshot_path(self.roots.snapshots, name)
        if path.exists():
            raise ApiError(409, f"snapshot {name!r} exists")
        from .storage import check_written, require_room  # (it imports this module)

        require_room(self, "a snapshot")
        save_bone(bone, path, generation=generation)
        check_written(self, path, "the snapshot")
        return snapshot_entry(path)

    def list_snapshots(self) -> list[dict]:
        return [snapshot_entry(p) for p in sorted(self.roots.snapshots.glob("*.bone.npz"))]

    # -- recording ----------------------------------------------------------------------------
    def start_recording(self, session_id: int, name: str | None, max_bytes: int) -> dict:
        session = self.ready(session_id)
        with session.lock:
            if session.recording is not None:
                raise ApiError(409, f"session {session_id} is already recording "
                                    f"({session.recording['name']})")
            bone = self.snapshot_bone(session_id)
            name = name or f"session-{session_id}-{time.strftime('%Y%m%d-%H%M%S')}"
            path = self.recordings_dir / (name if name.endswith(".burrrec")
                                          else name + ".burrrec")
            if path.exists():
                raise ApiError(409, f"recording {path.name} exists")
            from .storage import recording_cap, require_room  # (it imports this module)

            require_room(self, "a recording")
            path.mkdir(parents=True)
            try:
                from ..record.format import SNAPSHOT_NAME
                save_bone(bone, path / SNAPSHOT_NAME)
                # Capped by the budget's room left, so it stops cleanly at the budget.
                max_bytes = recording_cap(self, max_bytes)
                result = self.call("start_recording", session_id=session_id,
                                       path=str(path), snapshot_version=bone.grid.version,
                                       bone_name=session.source.source, max_bytes=max_bytes)
            except Exception:
                shutil.rmtree(path, ignore_errors=True)
                raise
            session.recording = {"name": path.name, "path": str(path), "max_bytes": max_bytes,
                                 **result}
            return session.recording

    def recording_status(self, session_id: int) -> dict | None:
        session = self.get(session_id)
        if session.recording is None:
            return None
        status = self.call("recording_status", session_id=session_id)
        return {**session.recording, **(status or {})}

    def stop_recording(self, session_id: int) -> dict:
        session = self.get(session_id)
        with session.lock:
            if session.recording is None:
                raise ApiError(409, f"session {session_id} is not recording")
            return self._stop_recording(session) or {}

    def _stop_recording(self, session: ManagedSession) -> dict | None:
        if session.recording is None:
            return None
        info = session.recording
        session.recording = None
        try:
            status = self.worker(session).call("stop_recording", session_id=session.id)
        except RuntimeError as exc:
            status = {"error": str(exc)}
        return {**info, **(status or {})}

    def list_recordings(self) -> list[dict]:
        out = []
        for path in sorted(self.recordings_dir.glob("*.burrrec")):
            size = sum(p.stat().st_size for p in path.iterdir() if p.is_file())
            out.append({"name": path.name, "bytes": size,
                        "complete": (path / "summary.json").exists(),
                        "replay": f"burrforce replay {path}"})
        return out

    # -- statistics ---------------------------------------------------------------------------
    def session_state(self, session_id: int, max_events: int = 100) -> dict:
        self.ready(session_id)
        return self.call("session_state", session_id=session_id,  # type: ignore[return-value]
                         max_events=max_events)

    # -- lifetime -----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop recordings, forget sessions, remove the shared bones (the caller stops the
        loop)."""
        self._loads.shutdown(wait=False, cancel_futures=True)
        self.history.stop()
        self.devices.close()
        for session in list(self.sessions.values()):
            try:
                with session.lock:
                    self._stop_recording(session)
            except Exception:
                pass
            self._drop_bone(session)
        self.sessions.clear()
        self.telemetry.close()
        shutil.rmtree(self.run_dir, ignore_errors=True)

    def resolve(self, source: str, kind: str | None = None, voxel_mm: float | None = None,
                spacing_mm: tuple[float, float, float] | None = None) -> BoneSource:
        try:
            return resolve(source, self.roots, kind, voxel_mm, spacing_mm)
        except SourceError as exc:
            raise ApiError(exc.status, str(exc)) from None


def journal_dir(data_dir: Path) -> Path:
    """Where the session journal (``journal``) keeps one folder per session."""
    return Path(data_dir).expanduser() / "journal" / "sessions"


def remove_stale_run_directories(base: Path, keep: Path) -> list[Path]:
    """Remove the shared-bone directories that servers killed with SIGKILL left in ``base``
    (``/dev/shm``, or the temporary directory): those whose owner process is gone, and
    empty ones without an owner (older servers). Returns what was removed."""
    removed = []
    for d in base.glob("burrforce-*"):
        # Only tempfile.mkdtemp's names (run_directory): not a bench's temporary folder.
        if d == keep or not d.is_dir() or not RUN_DIR_NAME.fullmatch(d.name):
            continue
        try:
            pid = int((d / OWNER_FILE).read_text())
        except (OSError, ValueError):
            pid = None
            try:
                if any(d.iterdir()):
                    continue  # not ours to judge
            except OSError:
                continue
        if pid is not None and _alive(pid):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # somebody else's live process
        return True
    return True


def later_stream(a: int | None, b: int | None) -> int | None:
    """The later of two stream numbers (serial order, mod 2**32), either may be None."""
    if a is None or b is None:
        return b if a is None else a
    return a if seq_after(a, b) else b


def next_stream_after(stream: int) -> int:
    """The first stream number a new hot loop may offer when the old one last reported
    ``stream`` as its next (uint32, never 0): ``STREAM_JUMP`` past it, so the streams it
    opened after that report are skipped too."""
    n = (int(stream) + STREAM_JUMP) % (1 << 32)
    return n or 1


def default_primary(materials: MaterialTable) -> int | None:
    """Label 1 if the bone has it (the thesis's cortical bone in every built-in table), else
    its first material that is not forbidden."""
    labels = [label for label, m in materials if not m.forbidden]
    if 1 in labels:
        return 1
    return labels[0] if labels else None


def with_overrides(materials: MaterialTable, primary: int | None,
                   overrides: dict) -> MaterialTable:
    """A copy of ``materials`` with the REST changes applied (key None: the primary
    material). Labels the bone does not have get the full material if one was given."""
    table = materials.copy()
    for label, changes in overrides.items():
        label = primary if label is None else label
        if label is None:
            continue
        if label in table:
            table.update(label, **changes)
        elif {"name", "us_n_mm2", "k"} <= set(changes):
            table.set(label, Material(**changes))
    return table


def snapshot_entry(path: Path) -> dict:
    name = path.name[: -len(".bone.npz")]
    return {"name": name, "source": f"snapshot:{name}", "bytes": path.stat().st_size,
            "created": path.stat().st_mtime}


def _bone_summary(reader: SharedBone, info: dict) -> dict:
    ref = reader.ref
    lo = np.array(ref.origin_mm)
    return {"name": ref.name, "format": ref.format, "kind": ref.kind,
            "shape": list(ref.shape), "spacing_mm": list(ref.spacing_mm),
            "origin_mm": lo.tolist(), "direction": [list(r) for r in ref.direction],
            "voxel_mm": info.get("voxel_mm"), "notes": list(ref.notes),
            "memory_bytes": ref.size_bytes}


def start_hot_loop(config: ServeConfig) -> HotLoopProcess:
    """The hot loop with no sessions yet (the control plane adds them)."""
    hot = HotLoopProcess(HotLoopConfig(config.host, config.udp_port, (), config.wake,
                                       config.realtime))
    hot.start()
    return hot


def start_hot_loops(config: ServeConfig) -> list[HotLoopProcess]:
    """``config.worker_count`` hot loops with no sessions yet, worker i on ``udp_port + i``
    (``hotloop.process.start_pool``)."""
    return start_pool(config.host, config.udp_port, config.worker_count, wake=config.wake,
                      realtime=config.realtime)
