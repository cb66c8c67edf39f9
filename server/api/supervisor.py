"""Keeps the hot loops alive: a dead or wedged loop is reported, replaced and refilled.

The hot loop is a process of its own (``hotloop.handle``, its main in ``hotloop.child``); it
can be killed (OOM killer, ``kill -9``, a crash in native code) or wedge (a tick that never
ends). The supervisor watches its exit status and its heartbeat; when either fails it says so
(console, log, health, metrics), kills what is left, starts a new loop on the same UDP port and
puts every session back with its id, key, parameters and carved bone
(``ControlPlane.rebuild``). The new loop is told which sessions are coming back before its
port opens: their datagrams go unanswered until each is back, never UNKNOWN_SESSION. Engines
then see their stream refused once (WRONG_STREAM), say hello again and go on with the same
key.

With a pool (``serve --workers``) each worker is watched and replaced on its own: a crash of
worker 2 rebuilds worker 2's sessions on worker 2's port and touches no other. One warm spare
serves the whole pool (it is re-warmed after use).

If a new loop cannot be started ``MAX_FAILED_STARTS`` times in a row, the supervisor gives
up and asks the server to exit with an error, so a process manager (docker's restart
policy, systemd) restarts the whole server: a server that cannot serve must not look alive.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from ..hotloop import HotLoopProcess
from ..hotloop.errors import CommandError
from .daemon import start_daemon, stop_daemon
from .metrics import LoopStats
from .plane import ControlPlane

log = logging.getLogger("burrforce.supervisor")

#: How often the loop's state is checked, s.
CHECK_INTERVAL_S = 0.05
#: A loop whose heartbeat (every 0.1 s) has been silent this long is wedged, s. Generous:
#: a busy 2-core machine can delay a thread by a second, and a restart costs every engine a
#: stream.
WEDGED_AFTER_S = 3.0
#: Consecutive failed starts before the server gives up and exits.
MAX_FAILED_STARTS = 5
#: Wait between failed starts, s (doubles each time).
RETRY_S = 0.5
#: After a restart, the next spare is warmed this much later, s.
SPARE_DELAY_S = 20.0
#: Exit status of ``burrforce serve`` when the hot loop cannot be brought back.
EXIT_LOOP_LOST = 3


@dataclass
class Restart:
    """One restart: why, when, and how long until the sessions were back."""

    reason: str
    at_s: float
    #: The index of the worker that was replaced.
    worker: int = 0
    sessions: int = 0
    recovery_s: float | None = None
    notes: tuple[str, ...] = ()

    def public(self) -> dict:
        return {"reason": self.reason, "at": self.at_s, "worker": self.worker,
                "sessions": self.sessions,
                "recovery_s": None if self.recovery_s is None else round(self.recovery_s, 3),
                "notes": list(self.notes)}


class Supervisor:
    """Watches ``plane.workers`` from a thread and replaces one when it dies or wedges.

    Args:
        plane: the control plane (a worker of its ``workers`` is replaced on a restart).
        stats: the statistics poller (it knows each session's last stream number).
        say: where console lines go (``burrforce serve`` prints them), besides the log.
        give_up: called once when the loop cannot be restarted (default: SIGTERM to this
            process, which stops ``serve``; it then exits with ``EXIT_LOOP_LOST``).
    """

    def __init__(self, plane: ControlPlane, stats: LoopStats,
                 say: Callable[[str], None] | None = None,
                 give_up: Callable[[], None] | None = None) -> None:
        self.plane = plane
        self.stats = stats
        self.say = say
        self.give_up = give_up or _terminate_self
        #: Per worker: "running", "restarting" or "lost" (gave up).
        self.states = ["running"] * len(plane.workers)
        self.restarts: list[Restart] = []
        self.failed_starts = 0
        #: A warm, unstarted loop that replaces a crashed one (``spawn_spare``).
        self.spare: HotLoopProcess | None = None
        self._spare_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def state(self) -> str:
        """The pool's: "lost" if a worker is, else "restarting" if one is, else
        "running"."""
        for state in ("lost", "restarting"):
            if state in self.states:
                return state
        return "running"

    def worker_restarts(self, index: int) -> int:
        """How many times worker ``index`` was replaced."""
        return sum(r.worker == index for r in self.restarts)

    # -- lifetime ---------------------------------------------------------------------------
    def start(self) -> None:
        self._thread = start_daemon(self._run, "burrforce-supervisor")

    def stop(self) -> None:
        stop_daemon(self._stop, self._thread)
        self._thread = None
        with self._spare_lock:
            spare, self.spare = self.spare, None
        if spare is not None:
            spare.stop()

    def _keep_spare(self, delay_s: float = 0.0) -> None:
        """Warm a spare loop in the background, after ``delay_s``. Its address is set when
        it takes a worker's place (``_take_spare``): one spare serves every worker."""
        def warm() -> None:
            if self._stop.wait(delay_s):
                return
            spare = HotLoopProcess(replace(self.plane.hot.config, udp_port=0, sessions=(),
                                            restoring=()))
            try:
                spare.spawn_spare()
            except RuntimeError as exc:
                log.warning("no spare hot loop (a restart will take longer): %s", exc)
                return
            with self._spare_lock:
                if self._stop.is_set() or self.spare is not None:
                    spare.stop()
                    return
                self.spare = spare

        threading.Thread(target=warm, name="burrforce-spare", daemon=True).start()

    def _take_spare(self, address: tuple[str, int],
                    restoring: tuple[int, ...] = ()) -> HotLoopProcess:
        # Every worker wakes ahead, and is scheduled, alike.
        like = replace(self.plane.hot.config, host=address[0], udp_port=address[1], sessions=(),
                       restoring=restoring)
        with self._spare_lock:
            spare, self.spare = self.spare, None
        if spare is not None and spare.is_alive() and spare.spare:
            # A spare reads its configuration only when started: it can take any port.
            spare.config = like
            return spare
        if spare is not None:
            spare.stop()
        return HotLoopProcess(like)

    def public(self) -> dict:
        """For /v1/health: the pool's state, worker 0's pid, and the restarts (of every
        worker; ``last_restart.worker`` says whose)."""
        last = self.restarts[-1].public() if self.restarts else None
        hot = self.plane.hot
        return {"state": self.state, "pid": hot.pid if hot.is_alive() else None,
                "restarts": len(self.restarts), "last_restart": last}

    # -- watching ---------------------------------------------------------------------------
    def _run(self) -> None:
        self._keep_spare()
        while not self._stop.wait(CHECK_INTERVAL_S):
            for index in range(len(self.plane.workers)):
                if self.states[index] == "lost":
                    continue
                reason = self.check(index)
                if reason is not None:
                    self.restart(reason, index)

    def check(self, index: int = 0) -> str | None:
        """Why worker ``index`` needs replacing now, or None while it is fine."""
        hot = self.plane.workers[index]
        if hot.wedged is not None:
            return f"not answering: {hot.wedged}"
        if not hot.is_alive():
            return f"exited ({_describe_exit(hot.exit_code)})"
        age = hot.heartbeat_age_s()
        if age > WEDGED_AFTER_S:
            return f"no heartbeat for {age:.1f} s (a tick that does not end)"
        return None

    def restart(self, reason: str, index: int = 0) -> bool:
        """Replace worker ``index``; True once its sessions are back. Gives up
        (``give_up``) after ``MAX_FAILED_STARTS`` failed starts in a row."""
        plane = self.plane
        old = plane.workers[index]
        record = Restart(reason, time.time(), index)
        self.states[index] = "restarting"  # before the record: a watcher sees both or neither
        self.restarts.append(record)
        t0 = time.monotonic()
        name = "HOT LOOP" if len(plane.workers) == 1 else f"HOT LOOP worker {index}"
        mine = set(plane.worker_sessions(index))
        restoring = tuple(s.id for s in plane.sessions.values() if s.id in mine and s.in_loop)
        self._tell(f"{name} {reason}: restarting it and its {len(restoring)} session(s)",
                   logging.ERROR)
        streams = self.stats.next_streams()
        address = old.address or (old.config.host, old.config.udp_port)
        old.kill()
        delay = RETRY_S
        while not self._stop.is_set():
            new = self._take_spare(address, restoring)
            try:
                new.start()
            except RuntimeError as exc:
                self.failed_starts += 1
                self._tell(f"{name.lower()} restart {self.failed_starts}/"
                           f"{MAX_FAILED_STARTS} failed: {exc}", logging.ERROR)
                if self.failed_starts >= MAX_FAILED_STARTS:
                    self.states[index] = "lost"
                    self._tell("giving up: the server stops so that its process manager "
                               "restarts it", logging.CRITICAL)
                    self.give_up()
                    return False
                self._stop.wait(delay)
                delay *= 2
                continue
            self.failed_starts = 0
            try:
                record.notes = tuple(plane.rebuild(new, streams, index))
            finally:
                _end_restore(new)
            # Numbers from the old loop are not the new one's.
            mine = plane.worker_sessions(index)
            self.stats.forget_sessions(mine if len(plane.workers) > 1 else None)
            record.sessions = sum(s.in_loop for s in plane.sessions.values()
                                  if s.id in set(mine))
            record.recovery_s = time.monotonic() - t0
            self.states[index] = "running"
            # Not at once: warming a spare is a second of both cores, which the sessions
            # just back need more (measured: p99 95 ms after a restart with it at once).
            self._keep_spare(SPARE_DELAY_S)
            self._tell(f"{name.lower()} back in {record.recovery_s:.2f} s with "
                       f"{record.sessions} session(s) (restart {len(self.restarts)})"
                       + "".join(f"; {n}" for n in record.notes), logging.WARNING)
            return True
        return False

    def _tell(self, text: str, level: int) -> None:
        if self.say is not None:
            self.say(text)
        else:
            log.log(level, text)

    # -- metrics ----------------------------------------------------------------------------
    def collect(self):  # the prometheus_client collector protocol
        restarts = CounterMetricFamily("burrforce_hotloop_restarts",
                                       "Times the hot loop died or wedged and was replaced")
        restarts.add_metric([], len(self.restarts))
        up = GaugeMetricFamily("burrforce_hotloop_up", "1 while the hot loop runs")
        up.add_metric([], 1.0 if self.state == "running" else 0.0)
        yield from (restarts, up)
        per_restarts = CounterMetricFamily("burrforce_worker_restarts", "Times each hot-loop "
                                           "worker died or wedged and was replaced",
                                           labels=["worker"])
        per_up = GaugeMetricFamily("burrforce_worker_up", "1 while the hot-loop worker runs",
                                   labels=["worker"])
        for index, state in enumerate(self.states):
            per_restarts.add_metric([str(index)], self.worker_restarts(index))
            per_up.add_metric([str(index)], 1.0 if state == "running" else 0.0)
        yield from (per_restarts, per_up)
        if self.restarts and self.restarts[-1].recovery_s is not None:
            recovery = GaugeMetricFamily("burrforce_hotloop_last_recovery_seconds",
                                         "From noticing the last failure to sessions back")
            recovery.add_metric([], self.restarts[-1].recovery_s)
            yield recovery


def _end_restore(hot: HotLoopProcess) -> None:
    """Tell a new loop its restore is over: a session that did not come back is answered
    UNKNOWN_SESSION from now on (if the loop died meanwhile, the next restart says it)."""
    try:
        hot.call("restored")
    except CommandError:
        pass


def _describe_exit(code: int | None) -> str:
    if code is None:
        return "status unknown"
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def _terminate_self() -> None:
    signal.raise_signal(signal.SIGTERM)


def worker_state(supervisor: Supervisor | None, worker: HotLoopProcess, index: int) -> str:
    """Hot-loop worker ``index``'s state as /v1/health reports it: the supervisor's
    ("running", "restarting", "lost"), or "down" for a dead loop it has not noticed yet.
    Without a supervisor, the process alone decides. Cheap: no command to the loop."""
    state = supervisor.states[index] if supervisor is not None else "running"
    if not worker.is_alive():
        return "down" if state == "running" else state
    return state
