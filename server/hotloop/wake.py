"""Waking ahead of a stream's next packet, so the loop is running when it arrives.

A loop blocked in ``epoll_wait`` pays the scheduler's wake-up when a datagram arrives: on this
project's reference machine (a 2-core VM) a paced round trip's two ends each spend ~55–80 µs
there, against a tick of ~67 µs. A haptic client sends at a steady rate, so its next packet's
arrival is predictable: the loop sleeps (with a microsecond timeout) until ``lead_us`` before
it, then polls without sleeping until it comes or ``lead_us`` after it. A datagram that arrives
while the loop polls is read within a microsecond or two. Measured with a bare echo paced at
1 kHz on that machine (one run each): p50 93–95 µs blocking, 35 µs waking 300 µs ahead (p99
132 µs against 207–221 µs).

The price is the polling: about ``lead_us`` per packet, 30 % of a core for one 1 kHz stream at
the default lead. ``cpu_share`` caps the loop's whole time awake, its work included: awake time
is earned at that share of wall time (a token bucket holding at most ``BUDGET_CAP_S``), and
without budget the loop blocks as before. So a loop with one or two streams polls for them,
and a loop whose streams keep it busy polls less and less, down to not at all: polling only
takes what the loop's own work leaves of its share, and the pool's other workers, the control
plane and the engine beside it keep the rest of the cores.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: How far ahead of a stream's predicted packet the loop starts polling, µs. The timer's own
#: wake-up is late by tens of µs on a VM; 300 µs covers it nearly always (150 µs: p99 302 µs
#: against 132 µs in the echo measurement above).
DEFAULT_LEAD_US = 250.0
#: The share of one core the loop may spend awake (working or polling) before it stops
#: polling, averaged over the budget's window.
DEFAULT_CPU_SHARE = 0.4
#: The polling budget holds at most this much, s: a quiet spell cannot save up for a long run
#: of polling later.
BUDGET_CAP_S = 0.02
#: Inter-arrival times outside this range are not a stream's period (a pause, a burst), s.
PERIOD_MIN_S = 0.0002
PERIOD_MAX_S = 0.02
#: Weight of a new interval in a stream's period (exponential average).
PERIOD_ALPHA = 0.125


#: Counter names :meth:`WakeAhead.count_into` writes.
WAKE_COUNTERS = ("wake_caught", "wake_missed", "wake_starved", "wake_spin_ms")


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


class WakeAhead:
    """Per-stream arrival prediction and the polling budget (one per loop; not thread-safe).

    Streams are keyed by anything hashable (the loop uses a peer socket's descriptor).
    """

    def __init__(self, config: WakeConfig, now_ns: int) -> None:
        self.lead_ns = int(config.lead_us * 1000)
        self.share = float(config.cpu_share)
        self.cap_ns = int(BUDGET_CAP_S * 1e9)
        self._budget_ns = 0
        self._budget_t = now_ns
        self._awake_since = now_ns
        self._last: dict[object, int] = {}
        self._period: dict[object, float] = {}
        #: Each stream's predicted next arrival, ns; absent once it was polled for in vain.
        self._due: dict[object, int] = {}
        #: Counters: polls that caught their packet, polls in vain, ns spent polling, and
        #: predictions skipped for want of budget.
        self.caught = 0
        self.missed = 0
        self.spin_ns = 0
        self.starved = 0

    def arrived(self, key: object, t_ns: int) -> None:
        """A datagram of stream ``key`` arrived at ``t_ns`` (monotonic)."""
        last = self._last.get(key)
        self._last[key] = t_ns
        if last is None:
            return
        interval = t_ns - last
        if not PERIOD_MIN_S * 1e9 <= interval <= PERIOD_MAX_S * 1e9:
            self._due.pop(key, None)  # a pause or a burst: predict again from the next one
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
        """(start, end) of the next polling window, monotonic ns, or None: no stream is
        predicted, or the loop's share of the core is spent; block until a datagram arrives.
        A window whose end has passed is dropped (its packet is late: the loop blocks for it).
        Charges the time awake since the last call (or since :meth:`woke`) to the budget."""
        self._budget_ns -= now_ns - self._awake_since
        self._awake_since = now_ns
        self._budget_ns = min(self.cap_ns,
                              self._budget_ns + int(self.share * (now_ns - self._budget_t)))
        self._budget_t = now_ns
        if not self._due:
            return None
        lead = self.lead_ns
        best = None
        for key, due in list(self._due.items()):
            if due + lead <= now_ns:
                del self._due[key]
                self.missed += 1
            elif best is None or due < best:
                best = due
        if best is None:
            return None
        if self._budget_ns <= 0:
            self.starved += 1
            return None
        return best - lead, best + lead

    def polled(self, start_ns: int, end_ns: int, caught: bool) -> None:
        """The loop polled from ``start_ns`` to ``end_ns`` (charged with the rest of its time
        awake); whether a datagram came."""
        self.spin_ns += max(0, end_ns - start_ns)
        if caught:
            self.caught += 1

    def count_into(self, counters: dict[str, int]) -> None:
        """Write the counters (``WAKE_COUNTERS``) into ``counters``."""
        counters["wake_caught"] = self.caught
        counters["wake_missed"] = self.missed
        counters["wake_starved"] = self.starved
        counters["wake_spin_ms"] = self.spin_ns // 1_000_000
