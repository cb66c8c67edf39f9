"""Streaming a trajectory at a fixed rate, and simple trajectories to stream."""

from __future__ import annotations

import gc
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from ..proto.messages import Notice
from .udp import IDENTITY, BurrClient, Result, ServerGone, now_us

log = logging.getLogger("burrforce.client")

#: Sleep until this close to a send time, then spin (sleep overshoots by ~0.1 ms or more).
SPIN_S = 0.0005


class Waypoint(NamedTuple):
    """One pose to send (engine frame and units)."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float] = IDENTITY
    rpm: float = 0.0
    spindle_on: bool = True
    flags: int = 0


@dataclass
class StreamResult:
    """What came back from a streamed trajectory.

    Attributes:
        results: one entry per waypoint: its Result, or None if no reply arrived.
        notices: notices received (the server refused those packets, or answered a hello).
        late_sends: sends more than one period behind schedule (this machine was busy).
        outages: times the server went away mid-stream (:class:`ServerGone`).
        outage_ticks: waypoints sent while it was away (from the tick the outage was noticed
            up to the first answer to one of them): their results are None.
    """

    results: list[Result | None]
    notices: list[Notice] = field(default_factory=list)
    late_sends: int = 0
    outages: int = 0
    outage_ticks: int = 0

    @property
    def lost(self) -> int:
        return sum(r is None for r in self.results)

    def rtt_us(self) -> np.ndarray:
        return np.array([r.rtt_us for r in self.results if r is not None])


def stream(client: BurrClient, waypoints: Iterable[Waypoint], rate_hz: float = 1000.0,
           on_result: Callable[[int, Result], None] | None = None,
           linger_s: float = 0.05,
           on_outage: Callable[[bool, int], None] | None = None) -> StreamResult:
    """Send ``waypoints`` at ``rate_hz`` on an absolute schedule (no drift), each stamped with
    its scheduled time, collecting replies as they arrive between sends; waits ``linger_s``
    after the last send for stragglers.

    ``on_result(index, result)`` is called as each reply arrives (keep it short: it runs
    between sends).

    The server going away does not end the stream: the outage is counted (``outages``,
    ``outage_ticks``) and reported to ``on_outage(True, index)`` (without it: a warning on
    the logger ``burrforce.client``); sending goes on on schedule, and when the server
    answers a waypoint sent since then ``on_outage(False, index)`` is called (or a second
    warning logged). A restarted server answers WRONG_STREAM, the client says hello and
    streams on (its first reply STALE, then cutting resumes).
    """
    if not 0.0 < rate_hz <= 100_000.0:
        raise ValueError(f"rate_hz must be in (0, 100000], got {rate_hz}")
    period = 1.0 / rate_hz
    index_of: dict[int, int] = {}
    results: list[Result | None] = []
    out = StreamResult(results)
    gone_since: list[int] = []  # [the index the outage was noticed at] while it lasts
    start_us = 0  # t_client_us of waypoint 0: waypoint k is stamped start_us + k periods

    def stamp_us(k: int) -> int:
        return start_us + round(k * period * 1e6)

    def gone(error: ServerGone) -> None:
        if gone_since:
            return
        k = len(results)
        gone_since.append(k)
        out.outages += 1
        if on_outage is not None:
            on_outage(True, k)
        else:
            log.warning("%s; sending on, waiting for it to come back (waypoint %d)", error, k)

    def back() -> None:
        k = len(results)
        out.outage_ticks += k - gone_since.pop()
        if on_outage is not None:
            on_outage(False, k)
        else:
            log.warning("the burrforce server at %s:%s answers again (waypoint %d)",
                        client.host, client.port, k)

    def collect(until: float) -> None:
        while True:
            remaining = until - time.perf_counter()
            try:
                message = client.receive(max(remaining - SPIN_S, 0.0) if remaining > 0
                                         else 0.0)
            except ServerGone as error:
                gone(error)
                continue
            if message is None:
                if time.perf_counter() >= until:
                    return
                continue
            # Only an answer to a waypoint sent since the outage was noticed says the server
            # is back. The socket reports a refusal ahead of datagrams that arrived before it:
            # a reply the old server sent just before it stopped is read after the refusal
            # (a client behind schedule sends without reading), and the next refusal would
            # count as a second outage.
            if gone_since and _answers_us(message) >= stamp_us(gone_since[0]):
                back()
            if isinstance(message, Notice):
                out.notices.append(message)
                continue
            i = index_of.pop(message.reply.seq, None)
            if i is not None:
                results[i] = message
                if on_result is not None:
                    on_result(i, message)

    # A full collection walks every object of the process: ~30 ms in a process that has
    # imported numba, i.e. 30 late packets. Frozen objects are skipped, so collections during
    # the stream only see what the stream allocates.
    gc.collect()
    gc.freeze()
    try:
        start = time.perf_counter()
        start_us = now_us()
        for k, w in enumerate(waypoints):
            due = start + k * period
            now = time.perf_counter()
            if now - due > period:
                out.late_sends += 1
            elif due > now:
                collect(due)
            # Stamped with its scheduled time: a late send must not look like a faster motion.
            try:
                seq = client.send(w.position, w.orientation, w.rpm, w.spindle_on, None,
                                  w.flags, stamp_us(k))
            except ServerGone as error:
                gone(error)  # the next send goes out: the OS reports each refusal once
                seq = None
            if seq is not None:
                index_of[seq] = k
            results.append(None)
            # Index entries of replies that never come must not pile up.
            if len(index_of) > 4 * rate_hz:
                index_of.pop(next(iter(index_of)))
        collect(time.perf_counter() + linger_s)
        if gone_since:  # still away at the end
            out.outage_ticks += len(results) - gone_since.pop()
    finally:
        gc.unfreeze()
    return out


def _answers_us(message: Result | Notice) -> int:
    """The t_client_us ``message`` echoes: the stamp of the pose it answers, µs."""
    return message.t_client_us if isinstance(message, Notice) else message.reply.t_client_us


def line(start: Sequence[float], end: Sequence[float], speed: float, rate_hz: float = 1000.0,
         orientation: Sequence[float] = IDENTITY, rpm: float = 0.0,
         spindle_on: bool = True) -> Iterator[Waypoint]:
    """Waypoints along a straight line at ``speed`` (length units per second), both ends
    included."""
    a = np.asarray(start, dtype=np.float64)
    b = np.asarray(end, dtype=np.float64)
    if not (np.isfinite(a).all() and np.isfinite(b).all()) or a.shape != (3,) \
            or b.shape != (3,):
        raise ValueError("start and end must be 3 finite numbers each")
    if not speed > 0.0 or not math.isfinite(speed):
        raise ValueError(f"speed must be positive, got {speed}")
    steps = max(1, math.ceil(float(np.linalg.norm(b - a)) / speed * rate_hz))
    q = tuple(float(x) for x in orientation)
    for k in range(steps + 1):
        p = a + (b - a) * (k / steps)
        yield Waypoint((float(p[0]), float(p[1]), float(p[2])), q, rpm, spindle_on)  # type: ignore[arg-type]
