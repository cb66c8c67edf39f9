"""Waking ahead of a stream's next packet, so the loop is running when it arrives.

A loop blocked in ``epoll_wait`` pays the scheduler's wake-up when a datagram arrives: on this
project's reference machine (a 2-core VM) a paced round trip's two ends each spend ~55–80 µs
there, against a tick of ~67 µs. A haptic client sends at a steady rate, so its next packet's
arrival is predictable: the loop sleeps (with a microsecond timeout) until ``lead_us`` before
it, then polls without sleeping until it comes or ``lead_us`` after it. A datagram that arrives
while the loop polls is read within a microsecond or two. Measured with a bare echo paced at
1 kHz on that machine (one run each): p50 93–95 µs blocking, 35 µs waking 300 µs ahead (p99
132 µs against 207–221 µs; 150 µs ahead: p99 302 µs, the timer's own wake-up being late).

Polling takes a core that others may need, so the loop polls only when that costs nobody:

- **Its CPU share.** ``cpu_share`` caps the loop's whole time awake, its work included: awake
  time is earned at that share of wall time (a token bucket holding at most
  ``BUDGET_CAP_S``). A loop with one stream polls for it (its tick plus about ``lead_us``
  per packet at 1 kHz); a loop whose streams keep it busy polls less and less, down to not
  at all.
- **Idle cores.** A window opens only while fewer other tasks are runnable than there are
  cores (``/proc/loadavg``'s running count): on a machine whose cores are all taken, by the
  pool's other workers, the engine, a load generator, the loop blocks as before.
- **Sharing its core.** While polling, the loop yields the core at each pass, so a client on
  the same core (an engine beside the server) sends its packet instead of waiting behind the
  poll. A yield that comes back later than ``lead_us`` means a task that does not block (a
  CPU-bound thread of the engine) holds the core: blocked, the loop would have preempted it
  when the datagram came (its priority is higher); polling, it waits for that task's slice.
  Measured with such a task on the loop's core: p99 4.2 ms polling against 0.4 ms blocking.
  A task that took the core once (a telemetry reader, a compiler) ends that one window;
  when it keeps happening (more than ``PREEMPT_ALLOWANCE_HZ``), the loop stops polling for
  ``BACKOFF_S``, doubling up to ``BACKOFF_MAX_S`` while it goes on: about one slow packet
  per back-off.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass

from .bucket import TokenBucket

#: How far ahead of a stream's predicted packet the loop starts polling, µs. The timer's own
#: wake-up is late by ~80–100 µs on this machine, so polling starts ~150 µs ahead.
DEFAULT_LEAD_US = 250.0
#: The share of one core the loop may spend awake (working or polling) and still poll,
#: averaged over the budget's window.
DEFAULT_CPU_SHARE = 0.4
#: The polling budget holds at most this much, s: a quiet spell cannot save up for a long run
#: of polling later.
BUDGET_CAP_S = 0.02
#: Inter-arrival times outside this range are not a stream's period (a pause, a burst), s.
PERIOD_MIN_S = 0.0002
PERIOD_MAX_S = 0.02
#: Weight of a new interval in a stream's period (exponential average).
PERIOD_ALPHA = 0.125
#: After a task held the loop's core through a yield: no polling for this long, s, doubling
#: while it happens again at each try, up to BACKOFF_MAX_S.
BACKOFF_S = 1.0
BACKOFF_MAX_S = 16.0
#: Preemptions that only end their window: this many a second on average, in bursts of
#: PREEMPT_BURST; more start the back-off.
PREEMPT_ALLOWANCE_HZ = 1.0
PREEMPT_BURST = 2.0
#: Counter names, in the dispatcher's counters: windows that caught a datagram; predictions
#: whose time passed without their datagram; times the loop blocked instead of polling for
#: want of CPU share, because every core was taken, or while backing off; polls cut short by
#: a task holding the core; ms polled; datagrams that came while the loop slept towards its
#: window (earlier than the lead); intervals that were no stream's period (a pause or a
#: burst: no prediction until the next).
WAKE_COUNTERS = ("wake_caught", "wake_missed", "wake_starved", "wake_busy", "wake_quiet",
                 "wake_preempted", "wake_poll_ms", "wake_early", "wake_irregular")


@dataclass(frozen=True)
class WakeConfig:
    """Attributes:
    lead_us: poll from this long before a stream's predicted packet until this long after
        it, µs; 0 turns waking ahead off (the loop blocks until a datagram arrives).
    cpu_share: the share of one core the loop may spend awake, its work included, and still
        poll, [0.01, 1].
    """

    lead_us: float = DEFAULT_LEAD_US
    cpu_share: float = DEFAULT_CPU_SHARE

    def __post_init__(self) -> None:
        if not (isinstance(self.lead_us, (int, float)) and math.isfinite(self.lead_us)
                and 0.0 <= self.lead_us <= 5000.0):
            raise ValueError(f"wake-ahead lead must be within [0, 5000] µs (0: off), got "
                             f"{self.lead_us!r}")
        if not (isinstance(self.cpu_share, (int, float)) and math.isfinite(self.cpu_share)
                and 0.01 <= self.cpu_share <= 1.0):
            raise ValueError(f"wake-ahead CPU share must be within [0.01, 1] of a core, got "
                             f"{self.cpu_share!r}")

    @property
    def enabled(self) -> bool:
        return self.lead_us > 0.0


DEFAULT_WAKE = WakeConfig()


class RunnableTasks:
    """Tasks runnable on the whole machine right now (``/proc/loadavg``'s running count, this
    one included), read into a buffer of its own (no file object, no bytes per call); None
    where there is no procfs."""

    def __init__(self, path: str = "/proc/loadavg") -> None:
        self._buf = bytearray(128)
        self._view = memoryview(self._buf)
        try:
            self._fd: int | None = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            self._fd = None

    def __call__(self) -> int | None:
        if self._fd is None:
            return None
        try:
            n = os.preadv(self._fd, (self._view,), 0)  # "0.52 0.58 0.59 2/345 6789\n"
        except OSError:
            return None
        buf = self._buf
        slash = buf.find(b"/", 0, n)
        i = slash - 1
        value = 0
        scale = 1
        while i >= 0 and 48 <= buf[i] <= 57:
            value += (buf[i] - 48) * scale
            scale *= 10
            i -= 1
        return value if slash > 0 and scale > 1 else None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


class WakeAhead:
    """Per-stream arrival prediction and when polling is allowed (one per loop; not
    thread-safe).

    Args:
        config: the lead and the CPU share.
        now_ns: monotonic ns.
        counters: where ``WAKE_COUNTERS`` are kept (the dispatcher's, read by ``stats``).
        cores: the machine's CPUs (``/proc/loadavg`` counts the whole machine's tasks, a
            container's too, so its quota is not the measure here).
        runnable: the machine's runnable tasks, this loop included (None: unknown, which
            never stops polling); default :class:`RunnableTasks`.

    Streams are keyed by anything hashable (the loop uses a peer socket's descriptor).
    """

    def __init__(self, config: WakeConfig, now_ns: int, counters: dict[str, int],
                 cores: int, runnable: Callable[[], int | None] | None = None) -> None:
        self.lead_ns = int(config.lead_us * 1000)
        self.share = float(config.cpu_share)
        self.cap_ns = int(BUDGET_CAP_S * 1e9)
        self.cores = max(1, int(cores))
        self.runnable = RunnableTasks() if runnable is None else runnable
        self.counters = counters
        for name in WAKE_COUNTERS:
            counters.setdefault(name, 0)
        self._budget_ns = 0
        self._budget_t = now_ns
        self._awake_since = now_ns
        self._poll_ns = 0
        self._quiet_until = now_ns
        self._backoff_ns = int(BACKOFF_S * 1e9)
        self._preempted_at = now_ns - int(BACKOFF_MAX_S * 1e9) * 4
        self._allowance = TokenBucket(PREEMPT_ALLOWANCE_HZ, PREEMPT_BURST)
        self._last: dict[object, int] = {}
        self._period: dict[object, float] = {}
        #: Each stream's predicted next arrival, ns; absent once its time passed.
        self._due: dict[object, int] = {}

    def arrived(self, key: object, t_ns: int) -> None:
        """A datagram of stream ``key`` arrived at ``t_ns`` (monotonic)."""
        last = self._last.get(key)
        self._last[key] = t_ns
        if last is None:
            return
        interval = t_ns - last
        if not PERIOD_MIN_S * 1e9 <= interval <= PERIOD_MAX_S * 1e9:
            self._due.pop(key, None)  # a pause or a burst: predict again from the next one
            self.counters["wake_irregular"] += 1
            return
        period = self._period.get(key)
        period = interval if period is None else period + PERIOD_ALPHA * (interval - period)
        self._period[key] = period
        self._due[key] = t_ns + int(period)

    def forget(self, key: object) -> None:
        """Stream ``key`` ended (its socket closed)."""
        self._last.pop(key, None)
        self._period.pop(key, None)
        self._due.pop(key, None)

    def woke(self, t_ns: int) -> None:
        """The loop came back from sleeping at ``t_ns``: it is awake from then."""
        self._awake_since = t_ns

    def next_poll(self, now_ns: int) -> tuple[int, int] | None:
        """(start, end) of the next polling window, monotonic ns, or None: block until a
        datagram arrives (no stream is predicted, the loop's share is spent, every core is
        taken, or it is backing off). A prediction whose window has passed is dropped. Charges
        the time awake since the last call (or since :meth:`woke`) to the budget."""
        self._budget_ns -= now_ns - self._awake_since
        self._awake_since = now_ns
        self._budget_ns = min(self.cap_ns,
                              self._budget_ns + int(self.share * (now_ns - self._budget_t)))
        self._budget_t = now_ns
        if not self._due:
            return None
        lead = self.lead_ns
        best = None
        expired = None
        for key, due in self._due.items():
            if due + lead <= now_ns:
                expired = key if expired is None else expired
            elif best is None or due < best:
                best = due
        if expired is not None:  # one at a time: a miss is rare, and no list per call
            del self._due[expired]
            self.counters["wake_missed"] += 1
        if best is None:
            return None
        if now_ns < self._quiet_until:
            self.counters["wake_quiet"] += 1
            return None
        if self._budget_ns <= 0:
            self.counters["wake_starved"] += 1
            return None
        running = self.runnable()
        if running is not None and running - 1 >= self.cores:
            self.counters["wake_busy"] += 1
            return None
        return best - lead, best + lead

    def polled(self, start_ns: int, end_ns: int, caught: bool) -> None:
        """The loop polled from ``start_ns`` to ``end_ns`` (charged with the rest of its time
        awake); whether a datagram came."""
        self._poll_ns += max(0, end_ns - start_ns)
        self.counters["wake_poll_ms"] = self._poll_ns // 1_000_000
        if caught:
            self.counters["wake_caught"] += 1

    def early(self) -> None:
        """A datagram came while the loop slept towards its window (before the lead)."""
        self.counters["wake_early"] += 1

    def close(self) -> None:
        """Release the runnable-task reader (when it is the default one)."""
        close = getattr(self.runnable, "close", None)
        if close is not None:
            close()

    def preempted(self, now_ns: int) -> None:
        """A yield came back more than the lead later: another task holds this core. Once in
        a while (``PREEMPT_ALLOWANCE_HZ``) this only ends the window: a task that ran once
        (a telemetry reader, a compiler) costs one packet. Beyond it, no polling for the
        back-off, which doubles each time this recurs within twice the back-off and starts
        again from BACKOFF_S after a longer quiet spell."""
        self.counters["wake_preempted"] += 1
        if self._allowance.take(now_ns):
            return
        if now_ns - self._preempted_at > 2 * self._backoff_ns:
            self._backoff_ns = int(BACKOFF_S * 1e9)
        self._preempted_at = now_ns
        self._quiet_until = now_ns + self._backoff_ns
        self._backoff_ns = min(2 * self._backoff_ns, int(BACKOFF_MAX_S * 1e9))
