"""The hot loop in its own process, and the handle the rest of the server holds on it.

Measured (design.md): a CPU-busy uvicorn in the loop's interpreter pushes its p99 round trip
from tens of µs to ~10 ms, so the loop gets a process of its own. The parent talks to it over
a pipe (commands: stats, add/remove sessions, stop); a thread in the child serves the pipe and
changes sessions between packets, under the loop's lock. Kernels are compiled (or loaded from
numba's cache) and every path of a tick run once before the port opens, so the first packet
is as fast as the thousandth.
"""

from __future__ import annotations

import gc
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from ..bone import Bone, BoneEngine, MaterialTable, ShaftParams, load_bone, phantom
from ..bone.engine import check_burr
from ..bone.loaders import LoadOptions
from ..bone.shared import SharedBone, SharedBoneRef
from ..haptics.stage import warm_up as warm_haptics
from ..model.params import CuttingParams
from ..realtime import HOT_LOOP_PRIORITY, enter_realtime, leave_realtime
from .dispatch import Dispatcher
from .errors import CommandError, SessionExists, classify
from .loop import LOOP_COUNTERS, open_socket, serve
from .session import Session, SessionConfig
from .telemetry import TelemetrySlot
from .wake import DEFAULT_WAKE, WakeConfig

PHANTOM_PREFIX = "phantom:"
#: The bone ``burrforce serve`` loads when none is named.
DEFAULT_BONE = "phantom:temporal"
#: First start with a cold numba cache compiles every kernel: minutes on a slow machine.
START_TIMEOUT_S = 600.0
#: A command's answer is due within this (adding a session passes its own, longer bound).
CALL_TIMEOUT_S = 30.0
#: The longest the packet thread waits for the GIL while a session is built, s (about).
GIL_TURN_S = 100e-6
#: The child's heartbeat thread takes the loop's lock and beats this often.
HEARTBEAT_INTERVAL_S = 0.1
#: The hot loop's niceness where it may raise its priority (``raise_priority``).
HOT_LOOP_NICE = -10
#: A spare's niceness while it warms (``child_main``): it must not slow the loops serving
#: sessions. Measured on a first start on two cores: the demo's round trips p50 1.4 ms, p99
#: 13 ms while the spare compiled at the loops' priority beside them.
SPARE_WARMING_NICE = 19
#: The first message to a spare (``HotLoopProcess.spawn_spare``), and the bone it warms on.
STANDBY = "standby"
SPARE_BONE = "phantom:workpiece"
SPARE_VOXEL_MM = 0.5


@dataclass(frozen=True)
class SessionSpec:
    """A session to create: which bone, which burr, which engine conventions, which key.

    Attributes:
        session_id: unsigned 32-bit id the client puts in every datagram.
        bone: ``phantom:NAME`` (``bone.PHANTOMS``), a bone file's path, or a bone the
            control plane has loaded into shared memory (``bone.shared.SharedBoneRef``).
        voxel_mm: a phantom's voxel size, mm (None: the phantom's default).
        key: the session key; None only for loopback development (no tags).
        config: frame, tool axis, features (``SessionConfig``).
        params: burr radius, spin, minimum cutting speed.
        shaft: the shaft's geometry.
        materials: the material table (None: the bone's own).
        publish: for a shared bone, keep the counters that let the control plane read it
            while it is cut.
        next_stream: the first stream number the session offers (None: a random one).
        telemetry: a telemetry file the control plane created and reads
            (``hotloop.telemetry``): the session's per-packet state lives in it. None:
            private memory.
    """

    session_id: int = 1
    bone: str | SharedBoneRef = DEFAULT_BONE
    voxel_mm: float | None = None
    key: bytes | None = None
    config: SessionConfig = field(default_factory=SessionConfig)
    params: CuttingParams = field(default_factory=CuttingParams)
    shaft: ShaftParams = field(default_factory=ShaftParams)
    materials: MaterialTable | None = None
    publish: bool = True
    next_stream: int | None = None
    telemetry: str | None = None


def load_session_bone(spec: SessionSpec) -> Bone:
    if isinstance(spec.bone, SharedBoneRef):
        return SharedBone(spec.bone, writable=True).bone()
    if spec.bone.startswith(PHANTOM_PREFIX):
        return phantom(spec.bone[len(PHANTOM_PREFIX):], spec.voxel_mm)
    if spec.voxel_mm is not None:
        raise ValueError("voxel_mm sets a phantom's voxel size, not a file's")
    return load_bone(Path(spec.bone), LoadOptions())


def build_session(spec: SessionSpec) -> Session:
    bone = load_session_bone(spec)
    materials = spec.materials if spec.materials is not None else bone.materials
    engine = BoneEngine(bone.grid, materials, spec.params, spec.shaft)
    telemetry = TelemetrySlot(spec.telemetry) if spec.telemetry is not None else None
    session = Session(spec.session_id, engine, spec.config, spec.key,
                      next_stream=spec.next_stream, telemetry=telemetry)
    session.publish_bone(spec.publish)
    return session


def bone_info(session: Session) -> dict:
    """What a client may want to know of a session's bone: its voxel size, mm."""
    return {"voxel_mm": float(min(session.engine.grid.spacing_mm))}


@dataclass(frozen=True)
class HotLoopConfig:
    """Where the hot loop listens, the sessions it starts with, whether it wakes ahead of
    its streams' packets (``hotloop.wake``), and whether its loop thread asks for the
    real-time scheduler (``server.realtime``; it then blocks for each datagram instead of
    waking ahead)."""

    host: str = "127.0.0.1"
    udp_port: int = 0
    sessions: tuple[SessionSpec, ...] = ()
    wake: WakeConfig = DEFAULT_WAKE
    realtime: bool = False


def usable_cores(cpu_max: str = "/sys/fs/cgroup/cpu.max") -> int:
    """Cores this process may keep busy: the CPUs it may run on, capped by a cgroup v2 CPU
    quota (``docker run --cpus 2``, a Kubernetes limit), which the affinity mask does not
    show: 32 host CPUs under a 2-core quota are 2."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota, period = Path(cpu_max).read_text().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):  # no cgroup v2 here, or unreadable: the affinity decides
        pass
    return cores


def default_workers() -> int:
    """Hot loops ``burrforce serve`` starts when not told: one per usable core, less one for
    the control plane (uvicorn, loads, the journal), at least one."""
    return max(1, usable_cores() - 1)


def worker_ports(udp_port: int, workers: int) -> list[int]:
    """Worker i's UDP port: ``udp_port + i`` (0: each takes an ephemeral one)."""
    return [0 if udp_port == 0 else udp_port + i for i in range(workers)]


def check_ports_free(host: str, udp_port: int, workers: int) -> None:
    """Fail before anything starts if a worker's port is taken (or past 65535): a pool that
    came up with a hole in its range would answer on ports nobody configured.

    Raises:
        RuntimeError: which port, which worker, and why.
    """
    if udp_port == 0:
        return
    last = udp_port + workers - 1
    if last > 65535:
        raise RuntimeError(f"{workers} workers need UDP ports {udp_port}..{last}: past 65535 "
                           "(lower --udp-port or --workers)")
    for i, port in enumerate(worker_ports(udp_port, workers)):
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                host, port, type=socket.SOCK_DGRAM)[0]
            with socket.socket(family, kind, proto) as probe:
                probe.bind(address)
        except OSError as exc:
            raise RuntimeError(
                f"UDP port {port} (worker {i} of {workers}: --udp-port {udp_port} + {i}) "
                f"cannot be bound on {host}: {exc.strerror or exc}") from None


def start_pool(host: str, udp_port: int, workers: int,
               timeout_s: float = START_TIMEOUT_S,
               wake: WakeConfig = DEFAULT_WAKE, realtime: bool = False) -> list[HotLoopProcess]:
    """Start ``workers`` hot loops with no sessions, worker i on ``udp_port + i`` (or an
    ephemeral port each when ``udp_port`` is 0), each waking ahead as ``wake`` says, and
    asking for the real-time scheduler with ``realtime``. The interpreters start and warm up
    side by side, not one after the other.

    Raises:
        ValueError: ``workers`` < 1.
        RuntimeError: a port is taken or a worker failed to start (every worker is stopped).
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    check_ports_free(host, udp_port, workers)
    pool = [HotLoopProcess(HotLoopConfig(host, port, (), wake, realtime))
            for port in worker_ports(udp_port, workers)]
    errors: list[str] = []

    def start(i: int) -> None:
        try:
            pool[i].start(timeout_s)
        except RuntimeError as exc:
            errors.append(f"worker {i}: {exc}" if workers > 1 else str(exc))

    try:
        for hot in pool:
            hot._spawn()
        threads = [threading.Thread(target=start, args=(i,), daemon=True)
                   for i in range(workers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    except BaseException:
        for hot in pool:
            hot.kill()
        raise
    if errors:
        for hot in pool:
            hot.stop()
        raise RuntimeError("; ".join(sorted(errors)))
    return pool


#: Thread pools of numerical libraries a loop never uses in parallel: an idle OpenBLAS worker
#: thread spins on a core the other loops and the control plane need.
SINGLE_THREADED = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                   "NUMBA_NUM_THREADS")


def child_environment() -> dict[str, str]:
    """The loop process's environment: ours (the numba cache among it), single-threaded
    numerics unless the user chose otherwise."""
    env = dict(os.environ)
    for name in SINGLE_THREADED:
        env.setdefault(name, "1")
    return env


class HotLoopProcess:
    """Starts, commands and stops the hot-loop process.

    Use as a context manager, or call :meth:`start` and :meth:`stop`. :meth:`call` is
    thread-safe.
    """

    def __init__(self, config: HotLoopConfig) -> None:
        self.config = config
        self.address: tuple[str, int] | None = None
        #: Per session id, what its bone is (``bone_info``), once started.
        self.bones: dict[int, dict] = {}
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._beat: socket.socket | None = None
        self._beat_s = 0.0
        self._exit_code: int | None = None
        #: Why the process was killed as wedged (None: it was not).
        self.wedged: str | None = None
        self._lock = threading.Lock()

    def start(self, timeout_s: float = START_TIMEOUT_S) -> tuple[str, int]:
        """Start the process; returns (host, port) once the port is open.

        The child is a fresh interpreter (``python -m burrforce.server.hotloop.child``), not a
        multiprocessing child: nothing of the parent is inherited or re-imported, so this
        works from any script, notebook or server. A second socket pair carries the child's
        heartbeat (``heartbeat_age_s``).

        Raises:
            RuntimeError: the loop failed to start (the message says why) or timed out.
        """
        if self._proc is None:
            self._spawn()
        proc, conn = self._proc, self._conn
        assert proc is not None and conn is not None
        try:
            conn.send(self.config)
            if not conn.poll(timeout_s):
                raise RuntimeError(f"the hot loop did not start within {timeout_s:g} s")
            message = conn.recv()
        except (EOFError, OSError):
            message = ("error", f"the hot-loop process exited (code {proc.poll()}) "
                                "before it was ready")
        except RuntimeError as exc:
            message = ("error", str(exc))
        if message[0] != "ready":
            self.kill()
            raise RuntimeError(message[1])
        self.address = (message[1], message[2])
        self.bones = message[3]
        self._beat_s = time.monotonic()
        return self.address

    def spawn_spare(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Start the process as a warm spare: interpreter, imports and every kernel loaded
        and run once (on a small bone), but no port and no sessions until :meth:`start`.
        A supervisor keeps one so that replacing a crashed loop costs a bind and the
        sessions' mapping, not a second of interpreter start-up.

        Raises:
            RuntimeError: the spare failed to warm up (the message says why) or timed out.
        """
        self._spawn()
        assert self._conn is not None
        try:
            self._conn.send(STANDBY)
            if not self._conn.poll(timeout_s):
                raise RuntimeError(f"the spare hot loop did not warm up within {timeout_s:g} s")
            message = self._conn.recv()
        except (EOFError, OSError):
            message = ("error", "the spare hot-loop process exited while warming up")
        except RuntimeError as exc:
            message = ("error", str(exc))
        if message[0] != "warm":
            self.kill()
            raise RuntimeError(message[1])

    @property
    def spare(self) -> bool:
        """A process is running but not started (``spawn_spare``)."""
        return self._proc is not None and self.address is None

    def _spawn(self) -> None:
        ours, theirs = socket.socketpair()
        beat_ours, beat_theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "burrforce.server.hotloop.child", str(theirs.fileno()),
                 str(beat_theirs.fileno())],
                pass_fds=(theirs.fileno(), beat_theirs.fileno()), stdin=subprocess.DEVNULL,
                env=child_environment())
        finally:
            theirs.close()
            beat_theirs.close()
        beat_ours.setblocking(False)
        self._proc, self._conn, self._beat = proc, Connection(ours.detach()), beat_ours

    def call(self, command: str, timeout_s: float = CALL_TIMEOUT_S, **kwargs: object) -> object:
        """Run a command in the loop process and return its result.

        A command that gets no answer within ``timeout_s`` leaves the pipe out of step (a late
        answer would be taken for the next command's): the process is then killed, and the
        supervisor (``api.supervisor``) starts a new one.

        Raises:
            CommandError: kind ``unavailable`` when the loop is not running, did not answer
                in time or exited; else the kind and message the command failed with in the
                loop (``hotloop.errors``).
        """
        with self._lock:
            # Once: the supervisor may kill the loop (and close the pipe) meanwhile; a closed
            # pipe then raises OSError here, which means the same as EOF.
            conn = self._conn
            if conn is None:
                raise CommandError("unavailable", "the hot loop is not running")
            try:
                conn.send((command, kwargs))
                if not conn.poll(timeout_s):
                    self.wedged = f"{command!r} got no answer within {timeout_s:g} s"
                    self.kill()
                    raise CommandError("unavailable",
                                       f"the hot loop is not answering ({self.wedged}): "
                                       "it was stopped and is being restarted")
                status, result = conn.recv()
            except (EOFError, OSError, BrokenPipeError):
                raise CommandError("unavailable", "the hot-loop process has exited") from None
        if status != "ok":
            raise CommandError.from_data(result)
        return result

    def heartbeat_age_s(self) -> float:
        """Seconds since the loop last showed it can take its lock (the child's heartbeat
        thread takes it every ``HEARTBEAT_INTERVAL_S``): a dead process or a tick that never
        ends stops the beats. ``inf`` when the loop is not running."""
        beat = self._beat
        if beat is None or self._proc is None:
            return math.inf
        try:
            while True:
                beat.recv(64)
                self._beat_s = time.monotonic()
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            return math.inf
        return time.monotonic() - self._beat_s

    @property
    def pid(self) -> int:
        if self._proc is None:
            raise RuntimeError("the hot loop is not running")
        return self._proc.pid

    def stats(self) -> dict:
        return self.call("stats")  # type: ignore[return-value]

    def is_alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def exit_code(self) -> int | None:
        """The process's exit status once it has ended (negative: killed by that signal)."""
        return self._proc.poll() if self._proc is not None else self._exit_code

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop the loop (it closes its socket) and wait for the process to end."""
        if self._proc is None:
            return
        try:
            self.call("stop")
        except RuntimeError:
            pass
        try:
            self._proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            pass
        self.kill()

    def kill(self) -> None:
        """End the process and close the pipes. SIGKILL: the loop ignores SIGTERM (its
        parent stops it through the pipe), a wedged one would not act on anything gentler,
        and it holds nothing that needs cleaning up (its shared bones' names are gone,
        devices have processes of their own)."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc is not None:
            self._exit_code = proc.returncode
        for pipe in (self._conn, self._beat):
            if pipe is not None:
                pipe.close()
        self._proc = None
        self._conn = None
        self._beat = None

    def __enter__(self) -> HotLoopProcess:
        if self._proc is None:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


# -- the child process --------------------------------------------------------------------------
def child_main(conn: Connection, beat: socket.socket | None = None) -> None:
    """The hot-loop process: read the config, build and warm the sessions, open the port,
    report ready, then serve packets (this thread), commands (another thread) and the
    heartbeat on ``beat`` (a third)."""
    # The parent owns Ctrl-C and SIGTERM (a terminal, `timeout` or systemd signal the whole
    # group) and stops the loop through the pipe, after zeroing what it must; were the loop
    # to die of them first, its supervisor would restart it in the middle of a shutdown.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raised = raise_priority()
    try:
        config = conn.recv()
        if config == STANDBY:
            # Warming takes a core for a second (a minute when it compiles, on a first start),
            # beside loops already serving: only at the lowest priority, and back to the
            # loop's before it may take a worker's place. Only where that way back is
            # allowed (it is whenever raising was).
            if raised:
                raise_priority(SPARE_WARMING_NICE)
            _warm_spare()
            if raised:
                raise_priority()
            conn.send(("warm",))
            config = conn.recv()
    except (EOFError, OSError):  # the parent went away before starting us: nothing to say
        return
    try:
        if not isinstance(config, HotLoopConfig):
            raise TypeError("expected a HotLoopConfig")
        dispatcher = Dispatcher()
        for spec in config.sessions:
            dispatcher.add(build_session(spec))
        dispatcher.warm_up()
        for session in dispatcher.sessions.values():
            session.publish_telemetry()
        # Every session may be switched to the coupled output later: no first coupled
        # packet may pay for loading its kernels.
        warm_haptics()
        sock = open_socket(config.host, config.udp_port)
    except (OSError, ValueError) as exc:  # a bad bone or address: the message says it all
        conn.send(("error", exc.strerror if isinstance(exc, OSError) and exc.strerror
                   else str(exc)))
        return
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    lock = threading.Lock()
    stopping = threading.Event()
    for name in LOOP_COUNTERS:  # counted by the loop; there before the first stats call
        dispatcher.counters.setdefault(name, 0)
    # Everything alive now lives for the process: keep the collector from walking it per
    # packet.
    gc.collect()
    gc.freeze()
    wake = config.wake
    # Measured (``bench sessions --workers 2``, 8 sessions, eight alternated pairs): p99
    # 0.74–0.98 ms against 1.77–3.52 ms at nice -10 when the loops contend for the cores
    # (README "Real-time scheduling").
    realtime = config.realtime and enter_realtime(HOT_LOOP_PRIORITY)
    if realtime:
        # Polling at a real-time priority would keep every normal task off the loop's core
        # while it polls (a yield hands the core only to real-time peers), and the
        # scheduler now runs the loop the moment a datagram wakes it.
        wake = WakeConfig(0.0, wake.cpu_share)
    host, port = sock.getsockname()[:2]
    conn.send(("ready", host, port,
               {sid: bone_info(s) for sid, s in dispatcher.sessions.items()}))
    # Threads inherit the scheduler: only the loop thread is real-time. The commands build
    # sessions (seconds of work) and must not take a core at that priority.
    commands = threading.Thread(target=_normal_priority(_serve_commands, realtime),
                                args=(conn, dispatcher, lock, stopping, sock),
                                name="burrforce-commands", daemon=True)
    commands.start()
    if beat is not None:
        threading.Thread(target=_normal_priority(_heartbeat, realtime),
                         args=(beat, lock, stopping),
                         name="burrforce-heartbeat", daemon=True).start()
    serve(sock, dispatcher, lock, stopping, wake)
    sock.close()
    commands.join(5.0)


def raise_priority(nice: int = HOT_LOOP_NICE) -> bool:
    """Ask the scheduler to run this process ahead of the control plane and whatever else
    shares the cores (nice ``nice``). Allowed for root, with CAP_SYS_NICE (podman:
    ``cap_add: [SYS_NICE]``) or an ``RLIMIT_NICE`` that permits it (docker/compose.yaml's
    ``ulimits: {nice: 30}``: docker gives added capabilities to root only); elsewhere the loop runs
    at the usual priority. Measured (``bench soak``): with a 100 000/s local flood on two
    cores, the usual priority let the flood's CPU push a session's p99 to 164 ms."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (PermissionError, OSError):
        return False
    return True


def _normal_priority(target, realtime: bool):
    """``target`` run in a thread that first leaves the real-time scheduler it inherited
    (keeping the loop's niceness), when ``realtime``."""
    if not realtime:
        return target

    def run(*args) -> None:
        leave_realtime()
        target(*args)

    return run


def _warm_spare() -> None:
    """Everything a first session needs, done before it comes: kernels loaded from the
    cache (or compiled) and run through every path of a tick on a small bone."""
    dispatcher = Dispatcher()
    dispatcher.add(build_session(SessionSpec(bone=SPARE_BONE, voxel_mm=SPARE_VOXEL_MM,
                                             publish=False)))
    dispatcher.warm_up()
    warm_haptics()
    del dispatcher
    gc.collect()


def _heartbeat(beat: socket.socket, lock: threading.Lock, stopping: threading.Event) -> None:
    """Beat while the loop can take its lock between two packets: a tick that never ends
    (or a dead process) is what silences it, not an idle socket."""
    beat.setblocking(False)
    while not stopping.wait(HEARTBEAT_INTERVAL_S):
        with lock:
            pass
        try:
            beat.send(b"\x01")
        except BlockingIOError:  # the parent has not read for a while: it only needs one
            pass
        except OSError:  # the parent is gone; the command thread stops the loop
            return


def _serve_commands(conn: Connection, dispatcher: Dispatcher, lock: threading.Lock,
                    stopping: threading.Event, sock: socket.socket) -> None:
    while True:
        try:
            command, kwargs = conn.recv()
        except (EOFError, OSError):  # the parent is gone: do not outlive it
            command, kwargs = "stop", {}
        except Exception as exc:  # an unpicklable command
            _send(conn, "error", CommandError("invalid", f"bad command: {exc}").as_data())
            continue
        if command == "stop":
            stopping.set()
            try:
                sock.shutdown(socket.SHUT_RDWR)  # wakes the blocking recvfrom
            except OSError:
                pass
            _send(conn, "ok", None)
            return
        try:
            result = _run_command(command, kwargs, dispatcher, lock)
        except Exception as exc:
            _send(conn, "error", classify(exc).as_data())
        else:
            _send(conn, "ok", result)


def _run_command(command: str, kwargs: dict, dispatcher: Dispatcher,
                 lock: threading.Lock) -> object:
    if command == "stats":
        return dispatcher.snapshot(lock, kwargs.get("tick_times_since"))
    if command == "session_state":
        with lock:
            session = _session(dispatcher, kwargs["session_id"])
            n = int(kwargs.get("max_events", 100))
            events = list(session.engine.events)[-n:] if n > 0 else []
            stats = session.stats()
            stats["haptics"] = session.haptics.snapshot()
        stats.pop("tick_times_us")
        stats["events"] = [e.__dict__ for e in events]
        return stats
    if command in ("add_session", "replace_session"):
        spec = kwargs["spec"]
        if not isinstance(spec, SessionSpec):
            raise TypeError("spec must be a SessionSpec")
        adding = command == "add_session"
        with lock:
            if adding and spec.session_id in dispatcher.sessions:
                raise SessionExists(f"session {spec.session_id} exists")
        # Loading and warming are the slow part: on a dispatcher of its own, outside the lock;
        # the session goes in (or replaces the old one) between two packets.
        with _short_gil_turns():
            session = build_session(spec)
            probe = Dispatcher()
            probe.add(session)
            probe.warm_up()
        old = None
        with lock:
            if adding:
                dispatcher.add(session)
            else:
                old = _session(dispatcher, spec.session_id)
                # Stream numbers go on from the old session's: one it offered is never
                # offered again (a captured hello and POSE would open it; SPEC 5.2).
                session.next_stream = old.next_stream
                dispatcher.sessions[spec.session_id] = session
            session.publish_telemetry()
        # The old bone is unmapped here, with the packet thread free to take the lock.
        del old
        return bone_info(session)
    if command == "configure":
        config = kwargs["config"]
        if not isinstance(config, SessionConfig):
            raise TypeError("config must be a SessionConfig")
        with lock:
            _session(dispatcher, kwargs["session_id"]).configure(config)
        return None
    if command == "set_engine":
        return _set_engine(dispatcher, lock, **kwargs)
    if command == "start_recording":
        return _start_recording(dispatcher, lock, **kwargs)
    if command in ("stop_recording", "recording_status"):
        with lock:
            session = _session(dispatcher, kwargs["session_id"])
            recorder = session.recorder
            if recorder is not None and command == "stop_recording":
                recorder.detach()
        if recorder is None:
            return None
        # Closing writes the last chunk: outside the lock, the loop goes on meanwhile.
        return recorder.close() if command == "stop_recording" else recorder.status()
    if command == "remove_session":
        with lock:
            return dispatcher.sessions.pop(kwargs["session_id"], None) is not None
    if command == "restart_stream":
        with lock:
            dispatcher.sessions[kwargs["session_id"]].end_stream()
        return None
    raise ValueError(f"unknown command {command!r}")


@contextmanager
def _short_gil_turns(interval_s: float = GIL_TURN_S) -> Iterator[None]:
    """While the command thread builds a session, the packet thread waits at most about
    ``interval_s`` for the GIL (the interpreter's default turn is 5 ms).

    What is left of a build is milliseconds of plain Python (objects, small arrays: the
    voxel work comes precomputed in a shared bone's file), in stretches up to ~0.5 ms
    (measured with ``bench.gil_probe``). A packet arriving meanwhile would wait for the
    stretch to end, up to a whole turn; shorter turns bound that wait instead."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def _session(dispatcher: Dispatcher, session_id: int) -> Session:
    try:
        return dispatcher.sessions[session_id]
    except KeyError:
        raise KeyError(f"no session {session_id}") from None


def _set_engine(dispatcher: Dispatcher, lock: threading.Lock, session_id: int,
                params: CuttingParams | None = None, shaft: ShaftParams | None = None,
                materials: MaterialTable | None = None, publish: bool | None = None) -> None:
    """Change a session's burr, shaft, materials or shared-memory publishing between two
    packets. Everything is checked before anything changes; the stream goes on.

    A material table with other forbidden flags needs new forbidden bricks: they are found
    here, outside the loop's lock (a pass over a shared bone's bricks, or the voxels of a
    private one; either kernel releases the GIL), not in the next tick."""
    with lock:
        engine = _session(dispatcher, session_id).engine
        grid, current = engine.grid, engine.materials
    bricks = None
    if materials is not None and not np.array_equal(materials.forbidden, current.forbidden):
        bricks = engine.forbidden_bricks_for(materials)
    with lock:
        session = _session(dispatcher, session_id)
        engine = session.engine
        if engine.grid is not grid:
            raise RuntimeError("the session's bone changed meanwhile; try again")
        new_shaft = shaft if shaft is not None else engine.shaft
        new_params = params if params is not None else engine.params
        check_burr(grid.spacing_mm, new_params, new_shaft)
        changed = new_shaft != engine.shaft or new_params != engine.params
        if new_shaft != engine.shaft:
            engine.shaft = new_shaft
        if new_params != engine.params:
            engine.params = new_params  # resets the coverage cache and the carve memory
        if changed:
            session.engine_changed()  # the hot path's copies (the coupling's shaft radius too)
        if materials is not None:
            engine.set_materials(materials, bricks)
        if publish is not None:
            session.publish_bone(publish)


def _start_recording(dispatcher: Dispatcher, lock: threading.Lock, session_id: int,
                     path: str, snapshot_version: int, bone_name: str = "",
                     max_bytes: int = 2 << 30) -> dict:
    """Attach a recorder between two packets (``record.start_recording``). The control plane
    has written the start snapshot at ``snapshot_version``; the bricks carved since then are
    saved here, under the lock, as the recording's start patch."""
    from ..record.recorder import start_recording

    with lock:
        session = _session(dispatcher, session_id)
        start_recording(session, path, bone_name=bone_name, max_bytes=max_bytes,
                        snapshot_version=snapshot_version)
        return {"start_version": session.engine.grid.version}


def _send(conn: Connection, status: str, result: object) -> None:
    try:
        conn.send((status, result))
    except (OSError, EOFError):
        pass
    except Exception as exc:  # an unpicklable result must not end the command thread
        try:
            conn.send(("error", CommandError(
                "internal", f"the result could not be sent: {exc}").as_data()))
        except Exception:
            pass
