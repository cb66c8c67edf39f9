"""The hot-loop workers behind the control plane: where a session runs, how it is called, and
how a restarted worker gets its sessions back.

The hot loops are a pool of worker processes (``serve --workers``), each on its own UDP port;
a new session is placed on the least-loaded worker (:meth:`WorkerPool.place`) and stays there
for life. Commands fail as ``(kind, message)`` data (``hotloop.errors.CommandError``);
:meth:`WorkerPool.call` raises the domain error of the kind (``errors.from_command``).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import replace

from ...proto.sequence import seq_after
from ..bone import MaterialTable
from ..bone.shared import SharedBoneRef, end_interrupted_tick
from ..hotloop import HotLoopConfig, HotLoopProcess, SessionSpec
from ..hotloop.errors import CommandError
from ..hotloop.handle import CALL_TIMEOUT_S, START_TIMEOUT_S
from ..hotloop.pool import start_pool
from .config import ServeConfig
from .errors import ApiError, Unavailable, from_command
from .sessions import ManagedSession, SessionTable, Settings

#: After a restart, stream numbers continue this far past the last one seen (SPEC 5.2): the
#: streams a loop opened after the last look are never offered again.
STREAM_JUMP = 1 << 16
#: Placement compares workers' measured tick work in steps of this, µs of tick per s (1 % of a
#: core): below it, load is noise (an idle session's stray tick) and session count decides.
WORK_STEP_US_PER_S = 10_000.0
#: Commands that map and warm a bone, or warm another burr's tick (a first start may compile
#: kernels, or wait for the background compile): the long timeout. The loop's heartbeat,
#: not the command's answer, tells a wedged loop meanwhile.
SLOW_COMMANDS = frozenset({"add_session", "replace_session", "set_engine"})


class WorkerPool:
    """The running hot loops, worker i at index i; thread-safe as the loops' handles are.

    Args:
        workers: the started hot loops (the caller owns starting and stopping them).
        sessions: the session table (a command naming a session goes to its worker).
        telemetry_path: where a session's loop writes its telemetry (``TelemetryReader``).
    """

    def __init__(self, workers: Sequence[HotLoopProcess], sessions: SessionTable,
                 telemetry_path: Callable[[int], str | None]) -> None:
        #: The supervisor replaces one in place when it restarts it (:meth:`rebuild`).
        self.workers: list[HotLoopProcess] = list(workers)
        if not self.workers:
            raise ValueError("a control plane needs at least one hot loop")
        self.sessions = sessions
        self.telemetry_path = telemetry_path
        #: Per session id, measured tick work, µs per s (``LoopStats.work_us_per_s``); set by
        #: whoever polls the loops' statistics. None: placement counts sessions only.
        self.work_us_per_s: Callable[[], dict[int, float]] | None = None

    def address(self, session: ManagedSession) -> tuple[str, int] | None:
        """The UDP endpoint of ``session``'s worker (None before it first started)."""
        return self.workers[session.worker].address

    def place(self, sessions: Sequence[ManagedSession]) -> int:
        """The worker a new session goes to, given the ``sessions`` there are: of the running
        workers (a dead worker's last statistics would make it look idle), the least measured
        tick work of its sessions (``WORK_STEP_US_PER_S`` steps), then the fewest sessions,
        then the lowest index."""
        n = len(self.workers)
        if n == 1:
            return 0
        alive = [i for i in range(n) if self.workers[i].is_alive()] or list(range(n))
        measured = self.work_us_per_s() if self.work_us_per_s is not None else {}
        work = [0.0] * n
        count = [0] * n
        for s in sessions:
            if 0 <= s.worker < n:
                count[s.worker] += 1
                work[s.worker] += measured.get(s.id, 0.0)
        return min(alive, key=lambda i: (int(work[i] // WORK_STEP_US_PER_S), count[i], i))

    def call(self, command: str, worker: int | None = None, **kwargs: object) -> object:
        """A hot-loop command, sent to ``worker``, default the worker of the session it names
        (``session_id`` or ``spec``).

        Raises:
            Invalid, NotFound, Conflict, Unavailable: the command failed
                (``errors.from_command``).
        """
        if worker is None:
            spec = kwargs.get("spec")
            sid = kwargs.get("session_id", getattr(spec, "session_id", None))
            session = self.sessions.get(sid)  # type: ignore[arg-type]
            worker = session.worker if session is not None else 0
        timeout_s = START_TIMEOUT_S if command in SLOW_COMMANDS else CALL_TIMEOUT_S
        try:
            return self.workers[worker].call(command, timeout_s=timeout_s, **kwargs)
        except CommandError as exc:
            raise from_command(exc) from None

    def spec(self, session: ManagedSession, ref: SharedBoneRef,
             materials: MaterialTable | None) -> SessionSpec:
        """What the loop is sent to add ``session`` on the bone ``ref`` with ``materials``."""
        key = bytes.fromhex(session.key_hex) if session.key_hex else None
        return SessionSpec(session.id, ref, None, key, session.effective_config(),
                           session.params, session.effective_shaft(),
                           materials=materials, publish=session.features.deltas,
                           next_stream=session.next_stream,
                           telemetry=self.telemetry_path(session.id))

    def push(self, session: ManagedSession, new: Settings, materials: bool = False) -> None:
        """Send the loop what ``new`` changes from what it has (if the session runs there): a
        Us change does not restart the stream, a frame change does. The session itself is
        not changed; the caller applies ``new`` once this returns.

        Raises:
            Invalid, NotFound, Unavailable: the loop refused or could not take it.
        """
        if not session.in_loop:
            return
        sent = session.sent
        kwargs: dict = {}
        if new.params != sent.get("params"):
            kwargs["params"] = new.params
        if new.effective_shaft() != sent.get("shaft"):
            kwargs["shaft"] = new.effective_shaft()
        if materials and new.materials is not None:
            kwargs["materials"] = new.materials.copy()
        if new.features.deltas != sent.get("publish"):
            kwargs["publish"] = new.features.deltas
        config = new.effective_config()
        if kwargs:
            self.call("set_engine", session_id=session.id, **kwargs)
            sent.update({k: v for k, v in kwargs.items() if k != "materials"})
        if config != sent.get("config"):
            self.call("configure", session_id=session.id, config=config)
            sent["config"] = config

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
        for session in self.sessions.values():
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
                spec = self.spec(session, replace(session.ref, path=path), session.materials)
                try:
                    self.call("add_session", spec=spec)
                except Unavailable as exc:  # the new loop died too: the next restart retries
                    notes.append(f"session {session.id}: not rebuilt yet ({exc.detail})")
                    continue
                except ApiError as exc:
                    session.in_loop = False
                    session.state, session.error = "failed", (
                        f"not rebuilt after the hot loop restarted: {exc.detail}")
                    notes.append(f"session {session.id}: {session.error}")
                    continue
                session.sent = sent_of(spec)
        return notes


def sent_of(spec: SessionSpec) -> dict:
    """What the loop has of a session once ``spec`` was added (``ManagedSession.sent``)."""
    return {"params": spec.params, "shaft": spec.shaft, "config": spec.config,
            "publish": spec.publish}


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


def start_hot_loop(config: ServeConfig) -> HotLoopProcess:
    """The hot loop with no sessions yet (the control plane adds them)."""
    hot = HotLoopProcess(HotLoopConfig(config.host, config.udp_port, (), config.wake,
                                       config.realtime))
    hot.start()
    return hot


def start_hot_loops(config: ServeConfig,
                    spawned: list[HotLoopProcess] | None = None) -> list[HotLoopProcess]:
    """``config.worker_count`` hot loops with no sessions yet, worker i on ``udp_port + i``
    (``hotloop.pool.start_pool``); ``spawned``: what ``hotloop.pool.spawn_pool`` made for
    the same config."""
    return start_pool(config.host, config.udp_port, config.worker_count, wake=config.wake,
                      realtime=config.realtime, spawned=spawned)
