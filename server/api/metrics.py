"""Prometheus metrics from the hot loops' statistics.

A poller thread asks the loops for their counters twice a second (a loop copies them between
two packets; quantiles and histograms are computed here) and keeps cumulative histograms of the
model-stage time from the ticks that happened since the last poll. With a pool of workers
(``serve --workers``) ``PoolStats`` merges theirs: counters summed, sessions side by side, and
each worker's own under ``workers`` (``burrforce_worker_*`` metrics, label ``worker``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence

import numpy as np
from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily

#: Histogram buckets of the model-stage time, µs (the upper bounds; +Inf is added).
TICK_BUCKETS_US = (25.0, 50.0, 100.0, 150.0, 200.0, 300.0, 500.0, 750.0, 1000.0, 2000.0,
                   5000.0)
POLL_INTERVAL_S = 0.5


class TickHistogram:
    """Cumulative bucket counts and sum of tick times (µs) for one session."""

    def __init__(self) -> None:
        self.counts = np.zeros(len(TICK_BUCKETS_US) + 1, dtype=np.int64)
        self.sum_us = 0.0

    def add(self, times_us: np.ndarray) -> None:
        if len(times_us):
            index = np.searchsorted(TICK_BUCKETS_US, times_us, side="left")
            self.counts += np.bincount(index, minlength=len(self.counts))
            self.sum_us += float(np.sum(times_us))


class LoopStats:
    """The latest statistics of the hot loop and the tick histograms (thread-safe).

    Args:
        fetch: ``hot.call("stats", tick_times_since=...)``-like callable.
    """

    def __init__(self, fetch: Callable[[dict[int, int]], dict]) -> None:
        self._fetch = fetch
        self._lock = threading.Lock()
        self.latest: dict | None = None
        self.histograms: dict[int, TickHistogram] = {}
        self._seen: dict[int, tuple[int, int]] = {}
        self.ticks_lost = 0
        self.poll_errors = 0
        #: Per session: (monotonic s, histogram sum µs) at the last poll, and the tick work
        #: between the last two polls, µs per s.
        self._work_mark: dict[int, tuple[float, float]] = {}
        self._work: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def poll(self) -> dict:
        with self._lock:
            since = dict(self._seen)
        stats = self._fetch(since)
        now_s = time.monotonic()
        with self._lock:
            live = set(stats["sessions"])
            for sid in list(self.histograms):
                if sid not in live:
                    del self.histograms[sid]
                    self._seen.pop(sid, None)
            for sid in list(self._work_mark):
                if sid not in live:
                    del self._work_mark[sid]
                    self._work.pop(sid, None)
            for sid, s in stats["sessions"].items():
                epoch, timed = s["tick_epoch"], int(s["ticks_timed"])
                seen_epoch, seen = self._seen.get(sid, (0, 0))
                if epoch != seen_epoch:  # a new session under this id, or counters reset
                    self.histograms.pop(sid, None)
                    seen = 0
                new = s.pop("new_tick_times_us", None)
                hist = self.histograms.setdefault(sid, TickHistogram())
                if new is not None:
                    hist.add(np.asarray(new))
                    self.ticks_lost += max(0, timed - seen - len(new))
                self._seen[sid] = (epoch, timed)
                mark = self._work_mark.get(sid)
                if mark is not None and now_s > mark[0]:
                    self._work[sid] = max(0.0, hist.sum_us - mark[1]) / (now_s - mark[0])
                self._work_mark[sid] = (now_s, hist.sum_us)
            self.latest = stats
        return stats

    def next_streams(self) -> dict[int, int]:
        """Per session, the next stream number the loop last reported: never 0 (unlike the
        open stream, 0 while none is) and past every number it handed out."""
        latest = self.latest or {}
        return {sid: int(s["next_stream"]) for sid, s in latest.get("sessions", {}).items()
                if s.get("next_stream")}

    def work_us_per_s(self) -> dict[int, float]:
        """Per session, the measured tick work between the last two polls, µs of model stage
        per s (what placing a new session on the least-loaded worker compares)."""
        with self._lock:
            return dict(self._work)

    def forget_sessions(self, session_ids: Sequence[int] | None = None) -> None:
        """Drop the per-session statistics of a loop that was replaced (the next poll brings
        the new one's): all of them, or those of ``session_ids`` (a pool's worker); the
        counters stay until then."""
        with self._lock:
            if self.latest is not None:
                sessions = ({} if session_ids is None else
                            {sid: s for sid, s in self.latest["sessions"].items()
                             if sid not in set(session_ids)})
                self.latest = {**self.latest, "sessions": sessions}

    def start(self) -> None:
        def run() -> None:
            while not self._stop.wait(POLL_INTERVAL_S):
                try:
                    self.poll()
                except Exception:
                    self.poll_errors += 1
        self._thread = threading.Thread(target=run, name="burrforce-stats", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)

    def collect(self):  # the prometheus_client collector protocol
        with self._lock:
            stats = self.latest
            histograms = {sid: (h.counts.copy(), h.sum_us)
                          for sid, h in self.histograms.items()}
        if stats is None:
            return
        packets = CounterMetricFamily(
            "burrforce_packets", "Datagrams by outcome (received, replied, noticed, and one "
            "reason per datagram not processed normally)", labels=["outcome"])
        counters = stats["counters"]
        for name, value in counters.items():
            if not name.startswith("wake_"):
                packets.add_metric([name], value)
        yield packets
        wake = CounterMetricFamily(
            "burrforce_wake_ahead", "The hot loops' waking ahead of predicted datagrams: "
            "caught (a datagram came while polling), missed (a prediction passed without its "
            "datagram), starved / busy / quiet (the loop blocked instead of polling: its CPU "
            "share was spent / every core was taken / it was backing off), preempted (a poll "
            "cut short by a task holding the core), early (a datagram came before the window "
            "opened), irregular (an interval that was no stream's period)", labels=["event"])
        for event in ("caught", "missed", "starved", "busy", "quiet", "preempted", "early",
                      "irregular"):
            wake.add_metric([event], counters.get(f"wake_{event}", 0))
        yield wake
        yield CounterMetricFamily(
            "burrforce_wake_poll_seconds", "Time the hot loops spent polling for predicted "
            "datagrams", value=counters.get("wake_poll_ms", 0) / 1000.0)
        hist = HistogramMetricFamily(
            "burrforce_tick_seconds", "Time of the bone stage (carve + force + shaft) per "
            "tick", labels=["session"])
        for sid, (counts, total) in sorted(histograms.items()):
            cumulative = np.cumsum(counts)
            buckets = [(f"{b * 1e-6:g}", int(c)) for b, c in zip(TICK_BUCKETS_US,
                                                                  cumulative, strict=False)]
            buckets.append(("+Inf", int(cumulative[-1])))
            hist.add_metric([str(sid)], buckets, total * 1e-6)
        yield hist
        sessions = stats["sessions"]
        accepted = CounterMetricFamily("burrforce_session_packets",
                                       "Per-session datagram outcomes",
                                       labels=["session", "outcome"])
        version = GaugeMetricFamily("burrforce_bone_version", "Bone version (ticks that "
                                    "removed bone)", labels=["session"])
        removed = GaugeMetricFamily("burrforce_removed_mm3", "Bone removed since the bone was "
                                    "loaded, mm³", labels=["session", "material"])
        force = GaugeMetricFamily("burrforce_last_force_newtons", "|F| of the last reply, N",
                                  labels=["session"])
        events = CounterMetricFamily("burrforce_forbidden_contacts", "Forbidden-structure "
                                     "contacts begun", labels=["session"])
        for sid, s in sorted(sessions.items()):
            label = str(sid)
            for name in ("accepted", "stale", "duplicate", "bad_value", "internal",
                         "hellos", "streams", "wrong_stream", "velocity_resets",
                         "teleports"):
                accepted.add_metric([label, name], s.get(name, 0))
            version.add_metric([label], s["bone_version"])
            for material, mm3 in s["removed_mm3"].items():
                removed.add_metric([label, material], mm3)
            force.add_metric([label], s["last_force_N"])
            events.add_metric([label], s["forbidden_events"])
        yield from (accepted, version, removed, force, events)
        up = GaugeMetricFamily("burrforce_sessions", "Sessions in the hot loop")
        up.add_metric([], len(sessions))
        yield up
        workers = stats.get("workers")
        if workers:
            per = CounterMetricFamily("burrforce_worker_packets", "Datagrams by outcome, per "
                                      "hot-loop worker", labels=["worker", "outcome"])
            held = GaugeMetricFamily("burrforce_worker_sessions", "Sessions in each hot-loop "
                                     "worker", labels=["worker"])
            for w in workers:
                label = str(w["index"])
                for name, value in w["counters"].items():
                    per.add_metric([label, name], value)
                held.add_metric([label], len(w["sessions"]))
            yield from (per, held)


class PoolStats:
    """The ``fetch`` of a ``LoopStats`` over a pool of hot loops: every worker's statistics,
    merged. Counters are summed, sessions (ids are unique across the pool) put side by side,
    and ``workers`` lists each one's (``index``, ``counters``, ``sessions``: its ids, ``up``:
    whether it answered this time). A worker that does not answer (dead, restarting) keeps
    its last answer, so what the supervisor reads of its sessions (their stream numbers)
    survives the crash; if none answers, the poll fails as with a single loop.

    Args:
        workers: returns the current workers (the supervisor replaces them).
    """

    def __init__(self, workers: Callable[[], Sequence]) -> None:
        self._workers = workers
        self._last: dict[int, dict] = {}
        #: Per worker, the process that gave the last answer and what the processes before
        #: it counted: a restarted worker counts from zero, and the pool's sums must not go
        #: back (Prometheus would read a drop as a reset of the whole pool's counters).
        self._hot: dict[int, object] = {}
        self._base: dict[int, dict[str, int]] = {}

    def __call__(self, since: dict[int, tuple[int, int]]) -> dict:
        answers: list[tuple[int, dict, bool]] = []
        error: Exception | None = None
        for i, hot in enumerate(self._workers()):
            try:
                answer = hot.call("stats", tick_times_since=since)
            except RuntimeError as exc:
                error = exc
                last = self._last.get(i)
                if last is not None:
                    answers.append((i, last, False))
                continue
            if i in self._hot and self._hot[i] is not hot and i in self._last:
                base = self._base.setdefault(i, {})
                for name, value in self._last[i]["counters"].items():
                    base[name] = base.get(name, 0) + value
            self._hot[i] = hot
            self._last[i] = answer
            answers.append((i, answer, True))
        if not any(up for _, _, up in answers):
            raise error if error is not None else RuntimeError("no hot loop")
        counters: dict[str, int] = {}
        sessions: dict[int, dict] = {}
        workers = []
        for i, answer, up in answers:
            base = self._base.get(i, {})
            for name, value in answer["counters"].items():
                counters[name] = counters.get(name, 0) + value + base.get(name, 0)
            for sid, s in answer["sessions"].items():
                if up:
                    sessions[sid] = s
                else:  # its tick times were counted when it last answered
                    sessions[sid] = {k: v for k, v in s.items() if k != "new_tick_times_us"}
            workers.append({"index": i, "counters": dict(answer["counters"]),
                            "sessions": sorted(answer["sessions"]), "up": up})
        return {"counters": counters, "time_ns": time.monotonic_ns(), "sessions": sessions,
                "workers": workers}


class DeviceCollector:
    """Prometheus metrics of the device loops (``plane.devices``), read at scrape time from
    their shared statistics."""

    def __init__(self, devices) -> None:
        self.devices = devices

    def collect(self):
        statuses = self.devices.statuses()
        counters = CounterMetricFamily(
            "burrforce_device", "Device loop counters (cycles, overruns, saturations, "
            "watchdog_trips, poses_sent, replies, error_replies, notices, refused, "
            "passivity_cycles)", labels=["session", "device", "counter"])
        rate = GaugeMetricFamily("burrforce_device_servo_rate_hz", "Measured servo rate",
                                 labels=["session", "device"])
        period = GaugeMetricFamily("burrforce_device_period_seconds", "Servo period "
                                   "percentiles", labels=["session", "device", "quantile"])
        live = GaugeMetricFamily("burrforce_device_live", "1 while a fresh coupling model is "
                                 "rendered (0: the watchdog holds zero force)",
                                 labels=["session", "device"])
        for sid, s in sorted(statuses.items()):
            labels = [str(sid), s["device"].partition(":")[0]]
            for name, value in s["counters"].items():
                counters.add_metric([*labels, name], value)
            rate.add_metric(labels, s["servo_rate_hz"] or 0.0)
            for q, key in (("0.5", "period_p50_us"), ("0.99", "period_p99_us")):
                if s[key] is not None:
                    period.add_metric([*labels, q], s[key] * 1e-6)
            live.add_metric(labels, 1.0 if s["live"] else 0.0)
        yield from (counters, rate, period, live)


def registry(stats: LoopStats, devices=None) -> CollectorRegistry:
    reg = CollectorRegistry(auto_describe=True)
    reg.register(stats)
    if devices is not None:
        reg.register(DeviceCollector(devices))
    return reg

