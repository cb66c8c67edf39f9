"""Each session's recent telemetry, kept by the control plane for a live session report.

One daemon thread samples every ready session's telemetry file (``api.telemetry``) at
``HISTORY_HZ`` and appends a row when the packet changed (``TelemetrySample.key``): the
server's receive time, the status bits and the hand force, the three series a
``report.SessionReport`` is built from. Nothing is asked of the hot loop and nothing is added
to its packet path (the thread runs in the control plane's process). A sample without the
tick ring costs 20–36 µs; with the thread's wake-ups the sampler took 1.2–1.4 % of a core for one
session streaming at ~1 kHz (shared 2-core machine), and wakes only every ``IDLE_S`` while no
session is ready.

Resolution: 100 Hz, not the stream's rate. A 1 kHz stream's ticks between two samples are not
seen: a force spike shorter than a sample period may be missed, and each row stands for the
~10 ms until the next. Cutting and contact time are sums over rows, so they are right to
about a sample per state change. The report says so in its ``notes``.

Bounded: ``MAX_ROWS`` rows per session (2 h at 100 Hz), grown in chunks of ``CHUNK_ROWS``
(an idle session holds none), then a ring that drops the oldest. A row is 18 bytes (t float64,
|F| float32, status uint16, installs uint32): 13.0 MB per session at most (207 MB for 16
sessions after 2 h of streaming each).

A session keeps its history across a hot-loop restart and a bone reload (its id and
``ManagedSession`` stay; ``installs`` in the rows says where the engine changed) and loses it
when it is deleted (``drop``; a new session under the same id starts afresh).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from .daemon import start_daemon, stop_daemon
from .sessions import ManagedSession, SessionTable
from .telemetry import TelemetryReader

log = logging.getLogger("burrforce.api")

#: Samples per second and session: a 20–36 µs sample every 10 ms (with the wake-ups, ~1.3 %
#: of a core for one session); faster buys little, since a report sums seconds of cutting,
#: not milliseconds, and 30–60 Hz is what a plot shows.
HISTORY_HZ = 100.0
#: Wait between passes while no session is ready, s.
IDLE_S = 0.1
#: Rows kept per session: 2 h at HISTORY_HZ.
MAX_ROWS = 720_000
#: Rows added at a time until MAX_ROWS (11 min at 100 Hz, 1.2 MB).
CHUNK_ROWS = 65_536
_DTYPE = np.dtype([("t_s", np.float64), ("force_N", np.float32), ("status", np.uint16),
                   ("installs", np.uint32)])
ROW_BYTES = _DTYPE.itemsize


@dataclass(frozen=True)
class HistoryView:
    """A copy of one session's history, oldest row first.

    Attributes:
        t_s: when the server received each packet, its monotonic clock (``time.monotonic``),
            s, float64 (n,).
        status: the reply's STATUS_* bits, int64 (n,).
        hand_force_N: |force| of the reply the hand got, N, float64 (n,).
        installs: int64 (n,), the install the row's packet was answered by
            (``TelemetrySample.installs``).
        dropped: rows older than the window, dropped (0: the history covers the session).
        hz: the sampling rate, Hz.
        wall_offset_s: ``time.time() − time.monotonic()`` when the view was taken (turns a
            ``t_s`` into a wall-clock time).
    """

    t_s: np.ndarray
    status: np.ndarray
    hand_force_N: np.ndarray
    installs: np.ndarray
    dropped: int
    hz: float
    wall_offset_s: float


class _Track:
    """One session's rows: preallocated in chunks of ``chunk_rows``, then a ring of
    ``max_rows``."""

    def __init__(self, owner: ManagedSession, max_rows: int = MAX_ROWS,
                 chunk_rows: int = CHUNK_ROWS) -> None:
        self.owner = owner
        self.max_rows = max_rows
        self.chunk_rows = chunk_rows
        self.rows = np.zeros(0, _DTYPE)
        self.written = 0  # rows appended in all (the ring's head is written % max_rows)
        self.key: tuple | None = None
        self.t_s = -np.inf

    @property
    def dropped(self) -> int:
        """Rows the ring has dropped."""
        return max(self.written - self.max_rows, 0)

    def append(self, t_s: float, force_N: float, status: int, installs: int) -> None:
        n = self.written
        if n >= len(self.rows) and len(self.rows) < self.max_rows:
            grown = np.zeros(min(len(self.rows) + self.chunk_rows, self.max_rows), _DTYPE)
            grown[:len(self.rows)] = self.rows
            self.rows = grown
        # Non-decreasing, whatever a restarted loop's clock reads.
        self.t_s = max(t_s, self.t_s)
        self.rows[n % self.max_rows] = (self.t_s, force_N, status, installs)
        self.written = n + 1

    def ordered(self) -> np.ndarray:
        n = self.written
        if n <= len(self.rows):
            return self.rows[:n].copy()
        head = n % self.max_rows
        return np.concatenate((self.rows[head:], self.rows[:head]))


class TelemetryHistory:
    """Samples the ready ones of ``sessions`` from one thread (:meth:`start`/:meth:`stop`) and
    keeps their histories; :meth:`view` copies one out. Thread-safe."""

    def __init__(self, sessions: SessionTable, reader: TelemetryReader,
                 hz: float = HISTORY_HZ) -> None:
        self.sessions = sessions
        self.reader = reader
        self.hz = float(hz)
        self._tracks: dict[int, _Track] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.errors = 0

    def start(self) -> None:
        """Start sampling (nothing to do without live telemetry)."""
        if not self.reader.available or self._thread is not None:
            return
        self._stop.clear()
        self._thread = start_daemon(self._run, "burrforce-history")

    def stop(self) -> None:
        stop_daemon(self._stop, self._thread)
        self._thread = None

    def drop(self, session_id: int) -> None:
        """Forget the session's history (it was deleted)."""
        with self._lock:
            self._tracks.pop(session_id, None)

    def view(self, session_id: int) -> HistoryView:
        """A copy of the session's history (empty if it has none yet)."""
        with self._lock:
            track = self._tracks.get(session_id)
            rows = track.ordered() if track is not None else np.zeros(0, _DTYPE)
            dropped = track.dropped if track is not None else 0
        return HistoryView(
            t_s=rows["t_s"].copy(), status=rows["status"].astype(np.int64),
            hand_force_N=rows["force_N"].astype(np.float64),
            installs=rows["installs"].astype(np.int64), dropped=dropped, hz=self.hz,
            wall_offset_s=time.time() - time.monotonic())

    # -- sampling -----------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.hz
        due = time.monotonic()
        while not self._stop.is_set():
            busy = True
            try:
                busy = self.sample_once() > 0
            except Exception:  # the sampler must outlive anything one session does
                self.errors += 1
                if self.errors <= 3:
                    log.exception("sampling the telemetry history")
            due += period if busy else IDLE_S
            now = time.monotonic()
            if due < now:  # late (a busy machine): skip the missed samples, no burst
                due = now
            self._stop.wait(due - now)

    def sample_once(self) -> int:
        """One pass over the ready sessions (the thread's); returns how many were ready."""
        sessions = self.sessions
        ready = 0
        for session in sessions.values():
            if session.state != "ready":
                continue
            ready += 1
            sample = self.reader.sample(session.id, ticks=False)
            # What an install leaves before its first packet (a zeroed pose) is no packet.
            if sample is None or not sample.packet:
                continue
            with self._lock:
                if sessions.get(session.id) is not session:
                    continue  # deleted meanwhile (drop ran, or will)
                track = self._tracks.get(session.id)
                if track is None or track.owner is not session:
                    track = self._tracks[session.id] = _Track(session)
                if sample.key == track.key:
                    continue
                track.key = sample.key
                track.append(sample.t_recv_s, sample.hand_force_magnitude_N, sample.status,
                             sample.installs)
        return ready
