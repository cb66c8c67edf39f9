"""The control plane: the services behind the REST API, built and wired in one place.

:class:`ControlPlane` holds no logic of its own beyond a session's life (create, delete)
that spans several services; each service owns its state:

- ``sessions`` (:class:`~.sessions.SessionTable`): the sessions as configured;
- ``pool`` (:class:`~.workers.WorkerPool`): the hot loops, placement, calls, rebuilds;
- ``loads`` (:class:`~.loading.BoneLoads`) and ``jobs``: bone loads and shared bones;
- ``settings`` (:class:`~.parameters.SessionSettings`): parameters, features, materials;
- ``recordings`` (:class:`~.recordings.Recordings`); ``storage`` (:class:`~.storage.Storage`);
- ``run_dir`` (:class:`~.housekeeping.RunDirectory`); ``telemetry``, ``history``, ``devices``.

Routes reach it through one FastAPI dependency (``deps.PlaneDep``). Everything raises the
domain errors of ``errors``; the app maps them to HTTP.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from ...proto.tag import new_key
from ..bone import Bone, Material, ShaftParams
from ..hotloop import HotLoopProcess, SessionConfig
from ..model.params import CuttingParams
from ..model.vibration import VibrationParams
from .config import ServeConfig
from .devices import DeviceAttachments
from .errors import ApiError, Unavailable
from .generation import bone_generation
from .history import TelemetryHistory
from .housekeeping import RunDirectory, journal_dir
from .jobs import Job, JobTable
from .loading import BoneLoads
from .models import Features, Parameters
from .parameters import SessionSettings
from .recordings import Recordings
from .sessions import ManagedSession, SessionTable, Settings
from .settings import settle
from .sources import BoneSource, SourceError, SourceRoots, resolve
from .storage import Storage
from .telemetry import TelemetryReader
from .workers import WorkerPool

log = logging.getLogger("burrforce.api")


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
        self.started_s = time.time()
        self.run_dir = RunDirectory()
        self.sessions = SessionTable(config.max_sessions)
        self.jobs = JobTable()
        #: Each session's live state, mapped from the hot loop (``telemetry``).
        self.telemetry = TelemetryReader(self.run_dir.path)
        self.pool = WorkerPool([hot] if isinstance(hot, HotLoopProcess) else hot,
                               self.sessions, self.telemetry.path)
        self.storage = Storage(config.data_dir, config.bone_library,
                               config.data_budget_bytes, self.sessions, self.jobs)
        self.recordings = Recordings(self.pool, self.storage)
        self.loads = BoneLoads(self.sessions, self.jobs, self.pool, self.recordings,
                               self.run_dir.path, self.storage.data_dir,
                               config.load_budget_bytes or None)
        #: Local haptic devices driven from sessions (``routes_devices``).
        self.devices = DeviceAttachments()
        self.settings = SessionSettings(self.pool, self.devices.attached)
        #: Each ready session's telemetry sampled at 100 Hz, for its live report.
        self.history = TelemetryHistory(self.sessions, self.telemetry)
        self.history.start()

    # -- the services' state, as the routes and the server read it ----------------------------
    @property
    def workers(self) -> list[HotLoopProcess]:
        """The hot loops, worker i at index i (the supervisor replaces one in place)."""
        return self.pool.workers

    @property
    def hot(self) -> HotLoopProcess:
        """Worker 0 (the only one with ``--workers 1``)."""
        return self.pool.workers[0]

    @property
    def work_us_per_s(self) -> Callable[[], dict[int, float]] | None:
        """Measured tick work per session, for placement (``WorkerPool.work_us_per_s``)."""
        return self.pool.work_us_per_s

    @work_us_per_s.setter
    def work_us_per_s(self, source: Callable[[], dict[int, float]] | None) -> None:
        self.pool.work_us_per_s = source

    @property
    def data_dir(self) -> Path:
        return self.storage.data_dir

    @property
    def roots(self) -> SourceRoots:
        return self.storage.roots

    @property
    def recordings_dir(self) -> Path:
        return self.storage.recordings_dir

    def address(self, session: ManagedSession) -> tuple[str, int] | None:
        """The UDP endpoint of ``session``'s worker (None before it first started)."""
        return self.pool.address(session)

    def place(self) -> int:
        """The worker a new session would go to now (``WorkerPool.place``)."""
        return self.pool.place(self.sessions.values())

    def worker_sessions(self, index: int) -> list[int]:
        """The ids of the sessions placed on worker ``index``."""
        return self.sessions.on_worker(index)

    def rebuild(self, hot: HotLoopProcess, streams: dict[int, int] | None = None,
                worker: int = 0) -> list[str]:
        """Worker ``worker`` replaced by ``hot``, its sessions moved in
        (``WorkerPool.rebuild``)."""
        return self.pool.rebuild(hot, streams, worker)

    def get(self, session_id: int) -> ManagedSession:
        """The session (NotFound)."""
        return self.sessions.find(session_id)

    def ready(self, session_id: int) -> ManagedSession:
        """The session with its bone loaded (NotFound, Conflict)."""
        return self.sessions.ready(session_id)

    @staticmethod
    def wait(job: Job, timeout_s: float = 600.0) -> bool:
        """Wait until ``job`` is done or failed (True) or ``timeout_s`` passes (False)."""
        return job.wait(timeout_s)

    def resolve(self, source: str, kind: str | None = None, voxel_mm: float | None = None,
                spacing_mm: tuple[float, float, float] | None = None) -> BoneSource:
        """A bone source checked against the server's folders (Invalid, NotFound, BadName)."""
        try:
            return resolve(source, self.storage.roots, kind, voxel_mm, spacing_mm)
        except SourceError as exc:
            raise exc.as_api_error() from None

    # -- a session's life ---------------------------------------------------------------------
    def create_session(self, session_id: int | None, bone: BoneSource, params: Parameters,
                       features: Features, authenticated: bool = True,
                       key_hex: str | None = None,
                       prepare: Callable[[ManagedSession], None] | None = None,
                       worker: int | None = None) -> tuple[ManagedSession, Job]:
        """Register a session and start loading its bone (``Job``). The session reaches the
        hot loop when the load finishes. ``prepare`` sets what a resumed session had
        (material changes, its carving) before the load starts; ``worker`` is the one it
        ran on (its engine streams to that port), kept if the pool still has it, else the
        session is placed (``WorkerPool.place``).

        Raises:
            Invalid: the parameters do not fit.
            Busy: the server holds ``max_sessions``.
            Conflict: ``session_id`` is in use.
        """
        defaults = Settings(CuttingParams(), ShaftParams(), VibrationParams(), SessionConfig(),
                            features)
        base = ManagedSession(0, None, bone, settle(defaults, params))
        if prepare is not None:
            prepare(base)
        if key_hex is None and authenticated:
            key_hex = new_key().hex()
        base.key_hex = key_hex if authenticated else None
        n = len(self.pool.workers)
        keep = worker if worker is not None and 0 <= worker < n else None
        self.sessions.register(base, session_id,
                               lambda others: keep if keep is not None
                               else self.pool.place(others))
        return base, self.loads.submit(base, "create", bone)

    def delete_session(self, session_id: int, keep_journal: bool = False) -> None:
        """Remove the session: its device zeroed, its recording closed, the loop's session
        removed, its journal (unless ``keep_journal``: a resume that failed keeps it for a
        human) and its bone freed (NotFound)."""
        session = self.get(session_id)
        self.devices.discard(session_id)  # its device is zeroed before the session goes
        with session.lock:
            self.recordings.end(session)

            def forget() -> None:
                # Before a new session may take the id: it must get a telemetry file of its
                # own (the old loop keeps writing its map of the unlinked one until removed).
                self.telemetry.discard(session_id)
                self.history.drop(session_id)

            self.sessions.remove(session_id, then=forget)
            # Now, not at the journal's next pass: a stop meanwhile must not resume it.
            if not keep_journal:
                shutil.rmtree(journal_dir(self.data_dir) / str(session_id), ignore_errors=True)
            try:
                if session.in_loop:
                    session.in_loop = False
                    self.pool.call("remove_session", worker=session.worker,
                                   session_id=session_id)
            except ApiError as exc:  # a dead loop has no session left to remove
                log.warning("removing session %s from the hot loop: %s", session_id,
                            exc.detail)
            finally:
                self.loads.drop_bone(session)

    def load_bone(self, session_id: int, bone: BoneSource, kind: str = "load") -> Job:
        """Replace a session's bone (a new source, a reset or a restore)."""
        return self.loads.replace(self.get(session_id), bone, kind)

    def reset(self, session_id: int) -> Job:
        """The bone as its source gives it (uncarved), and a new stream."""
        session = self.get(session_id)
        return self.loads.replace(session, session.source, "reset")

    def restart_stream(self, session_id: int) -> None:
        self.ready(session_id)
        self.pool.call("restart_stream", session_id=session_id)

    def session_state(self, session_id: int, max_events: int = 100) -> dict:
        """The loop's state of a ready session: bone version, removed volume, events."""
        self.ready(session_id)
        return self.pool.call("session_state", session_id=session_id,  # type: ignore
                              max_events=max_events)

    # -- settings -----------------------------------------------------------------------------
    def update_parameters(self, session_id: int, params: Parameters) -> ManagedSession:
        return self.settings.update_parameters(self.get(session_id), params)

    def update_features(self, session_id: int, features: Features) -> ManagedSession:
        return self.settings.update_features(self.get(session_id), features)

    def set_material(self, session_id: int, label: int, material: Material | None,
                     changes: dict | None = None) -> ManagedSession:
        return self.settings.set_material(self.ready(session_id), label, material, changes)

    def calibration_target(self, session_id: int, label: int | None) -> tuple[int, Material]:
        return self.settings.calibration_target(self.ready(session_id), label)

    def apply_calibration(self, session_id: int, label: int, us_n_mm2: float,
                          k: float | None, fit: dict | None, provenance: dict | None) -> dict:
        return self.settings.apply_calibration(self.ready(session_id), label, us_n_mm2, k,
                                               fit, provenance)

    # -- the bone and recordings --------------------------------------------------------------
    def snapshot_bone(self, session_id: int) -> Bone:
        """A consistent private copy of a ready session's bone as it is now."""
        return self.ready(session_id).snapshot_bone()

    def save_snapshot(self, session_id: int, name: str | None) -> dict:
        """Save the session's bone as snapshot ``name`` (``Storage.save_snapshot``)."""
        session = self.ready(session_id)
        generation = bone_generation(session)  # before the bone: generation.py
        return self.storage.save_snapshot(session.snapshot_bone(), name, session_id,
                                          generation)

    def start_recording(self, session_id: int, name: str | None, max_bytes: int) -> dict:
        return self.recordings.start(self.ready(session_id), name, max_bytes)

    def recording_status(self, session_id: int) -> dict | None:
        return self.recordings.status(self.get(session_id))

    def stop_recording(self, session_id: int) -> dict:
        return self.recordings.stop(self.get(session_id))

    def attach_device(self, session_id: int, make_config: Callable):
        """Drive a local device from a ready session (``DeviceAttachments.attach``)."""
        session = self.ready(session_id)
        address = self.address(session)
        if address is None:
            raise Unavailable(f"session {session_id}'s hot loop has no UDP endpoint yet")
        return self.devices.attach(session, address, make_config)

    # -- lifetime -----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop recordings, forget sessions, remove the shared bones (the caller stops the
        loops)."""
        self.loads.close()
        self.history.stop()
        self.devices.close()
        for session in self.sessions.values():
            try:
                with session.lock:
                    self.recordings.end(session)
            except Exception:
                pass
            self.loads.drop_bone(session)
        self.sessions.clear()
        self.telemetry.close()
        self.run_dir.remove()
