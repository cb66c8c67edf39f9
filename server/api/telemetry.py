"""Live per-session telemetry, read from the hot loop's own state in shared memory.

Each session's per-packet state lives in a telemetry file this process creates and the hot
loop maps (``hotloop.telemetry``). :class:`TelemetryReader` maps it read-only and samples it:
no command to the loop, no lock of the loop's, no pipe, and nothing added to the packet path.
The file outlives the hot loop: a loop the supervisor restarts, or a bone reload, builds the
session in the file's other slot and switches to it, so a reader follows by itself.

What a sample is (:class:`TelemetrySample`): the last packet the loop answered, as the loop
keeps it. Not an average, and not every packet: a 60 Hz reader of a 1 kHz stream sees one
packet in about 17. Torn reads are possible and accepted (``hotloop.telemetry``): a sample
may pair one packet's pose with the previous packet's reply.

Round trip: the server does not see when its reply reaches the client. ``residence_us`` is
the server's own part, t_send − t_recv of the packet (its monotonic clock, µs); the reply
echoes the client's ``t_client_us``, so the client's round trip is the client's to measure.

Staleness: the hot loop stamps t_recv with ``time.monotonic_ns()``, the system-wide
CLOCK_MONOTONIC this process's ``time.monotonic()`` reads too, so ``age_s`` (now − t_recv)
compares the two processes' times directly. While the supervisor restarts a loop the file
keeps the dead loop's last packet: ``age_s`` grows and ``loop`` (the caller's, from the
supervisor) says why.
"""

from __future__ import annotations

import logging
import math
import mmap
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...proto.messages import ERROR_NAMES, STATUS_NAMES
from ..hotloop import telemetry as block
from ..hotloop.stages import (
    K_A,
    K_REPLY,
    M_REPLY,
    M_STATUS,
    W_AXIS,
    W_LAST_FORCE,
    W_P,
    W_RPM,
    W_V,
)
from ..hotloop.wire import (
    R_AMPLITUDE,
    R_BONE_VERSION,
    R_ERROR,
    R_FORCE,
    R_FREQUENCY,
    R_POWER,
    R_REMOVED,
    R_RESISTIVE,
    R_SEQ,
    R_STATUS,
    R_T_CLIENT,
    R_T_RECV,
    R_T_SEND,
)

log = logging.getLogger("burrforce.api")
#: Copies of a slot tried before a torn one is returned (a reply written during the copy).
READ_ATTEMPTS = 3
#: The tick-time percentiles are recomputed at most this often per session, s: over the
#: 8192 kept times they cost ~0.1 ms, most of a sample's price.
PERCENTILES_EVERY_S = 0.25


@dataclass(frozen=True)
class TelemetrySample:
    """One session's latest packet, as the hot loop keeps it.

    Attributes:
        session_id: the session.
        installs: how many times a session was installed in this file (changes when the
            hot loop restarts or the bone is reloaded).
        packet: a reply to the session's latest packet is kept (False before the first
            packet, and if building a reply failed: ``seq``, ``t_client_us`` and ``error``
            are then None and ``residence_us`` 0; the pose fields and
            ``hand_force_magnitude_N`` are live either way). Every output keeps its reply:
            the raw output's kernel, and the coupled and limited outputs and recording
            sessions, whose replies are built in Python (``Session._keep_reply``).
        seq, t_client_us: the packet's sequence number and client time (echoed by the reply).
        t_recv_s: when the server received it, its monotonic clock, s.
        residence_us: t_send − t_recv, the server's part of the round trip, µs.
        error: the reply's error name ("ok").
        status: the reply's STATUS_* bits; ``status_names`` decoded. Only STATUS_STALE and
            STATUS_SLOW_SPINDLE while ``reply_current`` is False.
        reply_current: the reply's values (force, vibration, bone version, ...) are this
            packet's (False as ``packet``, or for a read torn across two packets).
        force_N: the reply's force (cut + shaft), the session's engine axes, N.
        force_server_N: the same force in the server frame (the frame of ``centre_mm``), N.
        resistive_N: the cutting force's (feed, lateral, normal) components, N.
        power_W: cutting power, W.
        hand_force_magnitude_N: |force| of the reply the hand got, N (every output).
        vibration_amplitude_N, vibration_frequency_Hz: the reply's vibration parameters.
        rpm: spindle speed, 0 with the spindle off.
        centre_mm: the burr centre, server frame, mm.
        axis: the tool axis (burr → handle), server frame, unit.
        velocity_mm_s: the feed velocity the model used, server frame, mm/s.
        bone_version: the bone version the reply reported.
        removed_mm3: bone removed by this packet's tick, mm³.
        tick_us_last: the model stage's time of the latest tick this reader saw, µs (None
            when it cannot tell which is latest).
        tick_us_p50, tick_us_p99: over the kept tick times (up to 8192), µs (None: none);
            recomputed at most every PERCENTILES_EVERY_S.
        age_s: how long ago the server received the packet, s, on the monotonic clock both
            processes read (None without ``packet``: no reply kept yet).
        loop: the supervisor's state of the hot loop serving the session ("running",
            "restarting", "lost", "down"), when the caller knows it (None: not asked).
    """

    session_id: int
    installs: int
    packet: bool
    seq: int | None
    t_client_us: int | None
    t_recv_s: float
    residence_us: int
    error: str | None
    status: int
    status_names: list[str]
    reply_current: bool
    force_N: list[float] | None
    force_server_N: list[float] | None
    resistive_N: list[float] | None
    power_W: float | None
    hand_force_magnitude_N: float
    vibration_amplitude_N: float | None
    vibration_frequency_Hz: float | None
    rpm: float
    centre_mm: list[float]
    axis: list[float]
    velocity_mm_s: list[float]
    bone_version: int | None
    removed_mm3: float | None
    tick_us_last: float | None
    tick_us_p50: float | None
    tick_us_p99: float | None
    age_s: float | None = None
    loop: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def key(self) -> tuple:
        """What changes with every packet, whichever output answered it."""
        return (self.installs, self.seq, self.t_recv_s, tuple(self.centre_mm), self.rpm,
                self.hand_force_magnitude_N)


class TickRing:
    """What a reader remembers of a session's tick ring, to find its newest entry."""

    def __init__(self) -> None:
        self.ticks: np.ndarray | None = None
        self.ticks_of = -1  # the install the kept ring is of
        self.last: int | None = None  # the newest entry found, ns
        self.percentiles: tuple[float, float] | None = None
        self.percentiles_s = -math.inf


class _Mapped(TickRing):
    """One telemetry file, mapped, and the tick ring as last seen."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        with open(path, "rb") as f:
            self.map = mmap.mmap(f.fileno(), block.FILE_BYTES, access=mmap.ACCESS_READ)


class TelemetryReader:
    """Creates the sessions' telemetry files in ``directory`` and samples them. Thread-safe.

    The control plane passes :meth:`path` in each ``SessionSpec`` (a restarted loop gets the
    same file) and calls :meth:`discard` when the session is deleted.
    """

    def __init__(self, directory: str | os.PathLike) -> None:
        self.directory = Path(directory)
        #: Telemetry files only in RAM (/dev/shm): a session's state is written on every
        #: packet, and pages of a disk-backed file (the run directory's fallback when
        #: /dev/shm is small) fault through the filesystem after each writeback.
        self.available = os.path.realpath(self.directory).startswith("/dev/shm/")
        self._maps: dict[int, _Mapped] = {}
        self._lock = threading.Lock()

    def _file(self, session_id: int) -> Path:
        return self.directory / f"telemetry-{session_id}.bin"

    def path(self, session_id: int) -> str | None:
        """The session's telemetry file, created (zeroed) if it does not exist; None when
        telemetry is not :attr:`available` or /dev/shm has no room for the file (the
        session then keeps private arrays: it streams, unwatched)."""
        if not self.available:
            return None
        p = self._file(session_id)
        if not p.exists():
            try:
                block.create(p)
            except OSError as exc:
                log.warning("session %s streams without live telemetry: %s", session_id, exc)
                Path(f"{p}.tmp").unlink(missing_ok=True)
                return None
        return str(p)

    def discard(self, session_id: int) -> None:
        """Forget the session's file (unmapped, removed)."""
        with self._lock:
            mapped = self._maps.pop(session_id, None)
            # Under the lock: a sample between the two would map the old file again and
            # keep it for a new session under the same id.
            self._file(session_id).unlink(missing_ok=True)
        if mapped is not None:
            mapped.map.close()

    def close(self) -> None:
        with self._lock:
            maps, self._maps = self._maps, {}
        for mapped in maps.values():
            mapped.map.close()

    def sample(self, session_id: int, *, ticks: bool = True,
               loop: str | None = None) -> TelemetrySample | None:
        """The session's latest packet, or None before a session was installed in its file
        (or when it has none). ``ticks=False`` skips the tick ring (the tick_us fields are
        None): most of a sample's cost, which a history sampled at 100 Hz does not need.
        ``loop`` is passed through to the sample."""
        with self._lock:
            mapped = self._maps.get(session_id)
            if mapped is None:
                p = self._file(session_id)
                if not p.exists():
                    return None
                mapped = self._maps[session_id] = _Mapped(p)
            return self._read(session_id, mapped, ticks, loop)

    def _read(self, session_id: int, mapped: _Mapped, with_ticks: bool,
              loop: str | None) -> TelemetrySample | None:
        head = block.header(mapped.map)
        for _ in range(READ_ATTEMPTS):
            state = int(head[block.H_STATE])
            installs, slot = block.installs_and_slot(state)
            if installs == 0:
                return None
            geometry, k, m, ticks = block.slot_arrays(mapped.map, slot)
            stamp = (int(m[M_REPLY + R_SEQ]), int(m[M_REPLY + R_T_RECV]))
            g, kc, mc = geometry.copy(), k.copy(), m.copy()
            if (int(head[block.H_STATE]), int(m[M_REPLY + R_SEQ]),
                    int(m[M_REPLY + R_T_RECV])) == (state, *stamp):
                break
        tick_last = p50 = p99 = None
        if with_ticks:
            tick_last, p50, p99 = newest_tick(mapped, installs, ticks.copy())
        return _sample(session_id, installs, g, kc, mc, tick_last, p50, p99, loop)


def newest_tick(ring: TickRing, installs: int,
                ticks: np.ndarray) -> tuple[float | None, float | None, float | None]:
    """(latest, p50, p99) of the tick ring ``ticks`` (int64 (TICK_TIMES_KEPT,), ns), µs;
    ``ring`` remembers the ring between calls. The ring's head is the loop's Python
    counter, not shared: the newest entry is found as the end of what changed since this
    reader's last look (or, on a ring not yet full, the last filled one: it is zeroed
    when the session is installed and filled in order). Nothing changed: the newest found
    before. None when it cannot tell: the whole ring changed (a lap or more since the
    last look). Wrong only when a new entry equals the one this reader last saw in its
    slot (ns times rarely repeat), which hides where the new entries end."""
    filled = ticks[ticks > 0]
    if filled.size == 0:
        ring.ticks, ring.ticks_of, ring.last = ticks, installs, None
        ring.percentiles = None
        return None, None, None
    now = time.monotonic()
    if (ring.percentiles is None or ring.ticks_of != installs
            or now - ring.percentiles_s >= PERCENTILES_EVERY_S):
        p50, p99 = np.percentile(filled, (50.0, 99.0)) / 1e3
        ring.percentiles, ring.percentiles_s = (float(p50), float(p99)), now
    p50, p99 = ring.percentiles
    last = None
    prev = ring.ticks if ring.ticks_of == installs else None
    if filled.size < ticks.size:
        last = int(ticks[filled.size - 1])
    elif prev is not None:
        changed = ticks != prev
        if not changed.any():
            last = ring.last
        elif not changed.all():
            if changed[0] and changed[-1]:  # the changed run wraps: it ends before a gap
                end = int(np.argmin(changed)) - 1
            else:
                end = int(np.flatnonzero(changed)[-1])
            last = int(ticks[end])
    ring.ticks, ring.ticks_of, ring.last = ticks, installs, last
    return (None if last is None else last / 1e3), p50, p99


def _server(g: np.ndarray, v: np.ndarray, point: bool) -> list[float]:
    """A grid-frame point (or vector) in the server frame: origin + direction · v."""
    direction = g[block.G_DIRECTION:block.G_DIRECTION + 9].reshape(3, 3)
    out = direction @ v
    if point:
        out = out + g[block.G_ORIGIN:block.G_ORIGIN + 3]
    return [float(x) for x in out]


def _sample(session_id: int, installs: int, g: np.ndarray, k: np.ndarray, m: np.ndarray,
            tick_last: float | None, p50: float | None, p99: float | None,
            loop: str | None) -> TelemetrySample:
    ri = m[M_REPLY:]
    rf = k[K_REPLY:]
    seq, t_recv = int(ri[R_SEQ]), int(ri[R_T_RECV])
    packet = t_recv != 0
    force = rf[R_FORCE:R_FORCE + 3]
    hand = float(k[W_LAST_FORCE])
    # reply_raw sets W_LAST_FORCE from the very floats it leaves in K_REPLY (the Python
    # outputs set only W_LAST_FORCE). Equal to rounding, not bit for bit: numba's kernel and
    # this may sum the squares differently (a dot product may fuse them).
    f0, f1, f2 = (float(x) for x in force)
    age = time.monotonic() - t_recv * 1e-6 if packet else None
    current = packet and math.isclose(math.sqrt(f0 * f0 + f1 * f1 + f2 * f2), hand,
                                      rel_tol=1e-12, abs_tol=1e-300)
    status = int(ri[R_STATUS]) if current else int(m[M_STATUS])
    return TelemetrySample(
        session_id=session_id, installs=installs, packet=packet,
        seq=seq if packet else None,
        t_client_us=int(ri[R_T_CLIENT]) if packet else None, t_recv_s=t_recv * 1e-6,
        residence_us=int(ri[R_T_SEND]) - t_recv if packet else 0,
        error=ERROR_NAMES.get(int(ri[R_ERROR]), str(int(ri[R_ERROR]))) if packet else None,
        status=status,
        status_names=[name for bit, name in STATUS_NAMES.items() if status & bit],
        reply_current=current,
        force_N=[float(x) for x in force] if current else None,
        # The reply turned the grid-frame force into engine axes with Aᵀ (A: engine → grid).
        force_server_N=_server(g, k[K_A:K_A + 9].reshape(3, 3) @ force, False)
        if current else None,
        resistive_N=[float(x) for x in rf[R_RESISTIVE:R_RESISTIVE + 3]] if current else None,
        power_W=float(rf[R_POWER]) if current else None,
        hand_force_magnitude_N=hand,
        vibration_amplitude_N=float(rf[R_AMPLITUDE]) if current else None,
        vibration_frequency_Hz=float(rf[R_FREQUENCY]) if current else None,
        rpm=float(k[W_RPM]),
        centre_mm=_server(g, k[W_P:W_P + 3], True),
        axis=_server(g, k[W_AXIS:W_AXIS + 3], False),
        velocity_mm_s=_server(g, k[W_V:W_V + 3], False),
        bone_version=int(ri[R_BONE_VERSION]) if current else None,
        removed_mm3=float(rf[R_REMOVED]) if current else None,
        tick_us_last=tick_last, tick_us_p50=p50, tick_us_p99=p99, age_s=age, loop=loop)
