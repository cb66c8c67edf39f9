"""The handle the rest of the server holds on a hot-loop process: start, command, watch, stop.

Measured (design.md): a CPU-busy uvicorn in the loop's interpreter pushes its p99 round trip
from tens of µs to ~10 ms, so the loop gets a process of its own (``child``). The parent talks
to it over a pipe: the config first (``loop_config.HotLoopConfig``, or
``loop_config.STANDBY`` for a warm spare), then commands (``commands.COMMANDS``), each
answered ``("ok", result)`` or ``("error", (kind, message))`` (``errors``); a second socket
pair carries the child's heartbeat. :class:`HotLoopProcess` is thread-safe and raises
``errors.CommandError``.
"""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

from .errors import CommandError
from .loop_config import STANDBY, HotLoopConfig

#: First start with a cold numba cache compiles every kernel: minutes on a slow machine.
START_TIMEOUT_S = 600.0
#: A command's answer is due within this (adding a session passes its own, longer bound).
CALL_TIMEOUT_S = 30.0
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
        #: Per session id, what its bone is (``spec.bone_info``), once started.
        self.bones: dict[int, dict] = {}
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._beat: socket.socket | None = None
        self._beat_s = 0.0
        self._exit_code: int | None = None
        #: Why the process was killed as wedged (None: it was not).
        self.wedged: str | None = None
        #: Held by a command's round trip; reentrant: a call that times out kills the loop.
        self._lock = threading.RLock()
        self._config_sent = False

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
            self.spawn()
        proc, conn = self._proc, self._conn
        assert proc is not None and conn is not None
        try:
            if not self._config_sent:
                self.send_config()
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
        self.spawn()
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

    def spawn(self) -> None:
        """Start the process, which then waits for its config (:meth:`start`) or to warm up
        as a spare (:meth:`spawn_spare`). :meth:`start` spawns by itself; a pool spawns every
        worker first so that their interpreters start side by side (``pool.start_pool``)."""
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

    def send_config(self) -> None:
        """Send the config to the spawned process, which then warms up, opens its port and
        reports ready by itself; :meth:`start` waits for that (``pool.spawn_pool`` sends it
        at once, so the warm-up overlaps the parent's own start-up)."""
        assert self._conn is not None, "spawn first"
        self._conn.send(self.config)
        self._config_sent = True

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
            # The supervisor may kill the loop meanwhile: the read then ends in EOF, and the
            # pipe is closed only after this block (``kill``).
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
        thread takes it every ``child.HEARTBEAT_INTERVAL_S``): a dead process or a tick that never
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
        # Only once no command is reading the pipe (its read ends now: the process is gone).
        # Closed under a reader, its descriptor could be given to the next loop's pipe, and
        # the reader would take that loop's bytes as its own answer.
        with self._lock:
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
