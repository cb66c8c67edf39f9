"""The load generator of ``burrforce bench sessions``: one thread that drives many stations'
sessions at 1 kHz each through the real protocol, and what it measured.

Each station has its own clock (:func:`station_clocks`: aligned, or independent phases and
rates); its POSEs are encoded and signed before the schedule starts (:func:`drive` then only
sends and receives); round trips are taken from the kernel's arrival stamps where it gives
them (``SO_TIMESTAMPNS``); :func:`tally` turns the records into a row (round trips, lost,
late, the generator's own lateness). See ``bench.sessions`` for the definitions.
"""


from __future__ import annotations

import ctypes
import gc
import os
import selectors
import socket
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ...client.udp import SessionRules
from ...proto.messages import HELLO_STREAM, NEW_STREAM, SEQ_MODULUS, STATUS_CUTTING, Notice
from .latency import HELLO_TRIES, RPM, GrooveCut
from .procstat import cpu_s

PERIOD_NS = 1_000_000
#: After the last send, replies are still read for this long before the rest count as lost.
DRAIN_S = 0.5
#: Linux's SO_TIMESTAMPNS (= SCM_TIMESTAMPNS; asm-generic and x86), which Python does not name.
SO_TIMESTAMPNS = 35
TIMESPEC = struct.Struct("@qq")
PR_SET_TIMERSLACK, PR_GET_TIMERSLACK = 29, 30
PHASES = ("independent", "aligned")
#: Independent stations' clock rates differ by up to this much (crystal tolerance, or a
#: software loop's own rate error, which is larger): over a 10 s window, phases slide by 0.5 ms.
RATE_SPREAD_PPM = 50.0
RECV_BYTES = 2048
@dataclass
class Stream:
    """One session as the generator drives it: its socket, rules, cut and records."""

    session: int
    worker: int | None
    sock: socket.socket
    rules: SessionRules
    cut: GrooveCut = field(default_factory=GrooveCut)
    seq0: int = 0
    send_ns: np.ndarray | None = None  # (ticks,) monotonic ns, 0: not sent
    datagrams: list[bytes] = field(default_factory=list)  # one POSE per tick, encoded
    #: (kernel arrival ns on the monotonic clock or 0, user-space read ns, datagram)
    replies: list = field(default_factory=list)


@contextmanager
def _generator_scheduling(report: dict) -> Iterator[None]:
    """For this thread while it drives, restored after: the hot loop's priority where it
    may be had (the loop raises its own, and a saturated loop would otherwise starve the
    generator, which then measures its own lateness rather than the server), and
    ``select`` waking within ~1 µs of its timeout rather than Linux's default 50 µs slack
    (the sends are due every 1 ms, and the generator must not spin to keep them). Where
    allowed, SCHED_FIFO above the loops' priority, with or without ``--realtime``: the
    generator stands for stations on other machines, whose sends the server's load does not
    delay. Below the loops it would be preempted by them between its send stamp and its
    send (measured: p99.9 6.7–8.6 ms against 4.1–5.5 at 8 sessions), and its late sends
    would spread the burst it is meant to send. ``report["generator_nice"]`` gets the
    niceness it ran at, ``report["generator_realtime"]`` whether it was SCHED_FIFO."""
    from ..hotloop.child import raise_priority
    from ..realtime import HOT_LOOP_PRIORITY, enter_realtime, leave_realtime

    nice = os.getpriority(os.PRIO_PROCESS, 0)
    raised = raise_priority()
    report["generator_nice"] = os.getpriority(os.PRIO_PROCESS, 0)
    fifo = report["generator_realtime"] = enter_realtime(HOT_LOOP_PRIORITY + 1)
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
        old = prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
        prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(1000), 0, 0, 0)
    except (OSError, AttributeError):
        prctl = None
    try:
        yield
    finally:
        if fifo:
            leave_realtime()
        if prctl is not None and old > 0:
            prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(old), 0, 0, 0)
        if raised:
            os.setpriority(os.PRIO_PROCESS, 0, nice)


def kernel_timestamps(sock: socket.socket) -> bool:
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def open_stream(host: str, port: int, session: int, key_hex: str | None,
          worker: int | None) -> Stream:
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect((host, port))
    # Seconds of replies fit, should the generator fall behind for a while.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    return Stream(session, worker, sock, SessionRules(session, key_hex, 1))


def handshake(s: Stream) -> None:
    """Hello → NEW_STREAM, untimed, blocking."""
    s.sock.settimeout(0.25)
    for _ in range(HELLO_TRIES):
        seq, data = s.rules.datagram((12.0, 0.0, 20.0), (0.0, 0.0, 0.0, 1.0), RPM, True, None,
                                     0, None)
        s.sock.send(data)
        try:
            while True:
                m = s.rules.accept(s.sock.recv(RECV_BYTES), time.monotonic_ns() // 1000)
                if s.rules.stream != HELLO_STREAM:
                    s.sock.setblocking(False)
                    return
                if isinstance(m, Notice) and m.seq == seq and m.error != NEW_STREAM:
                    raise RuntimeError(f"session {s.session} refused the hello: error {m.error}")
        except TimeoutError:
            continue
    raise RuntimeError(f"session {s.session} never answered a hello")


def percentiles(values: np.ndarray, qs: tuple[float, ...]) -> list[float | None]:
    if len(values) == 0:
        return [None for _ in qs]
    return [float(v) for v in np.percentile(values, qs)]


def _encode_all(s: Stream, ticks: int) -> None:
    """Encode (and sign) the stream's POSE for every tick of the schedule before it starts:
    the generator then only sends during the run, so its own CPU, which shares the machine
    with the server it measures, is a send and a receive per packet. A POSE's ``t_client_us``
    is its deadline on the schedule (µs from its start); the cut advances 1 ms per tick."""
    s.datagrams = []
    for k in range(ticks):
        t_us = k * PERIOD_NS // 1000
        position, flags = s.cut.pose(t_us, False)
        s.datagrams.append(s.rules.datagram(position, s.cut.orientation, RPM, True, None,
                                            flags, t_us)[1])


def station_clocks(n: int, phases: str, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``n`` sessions' schedule: ``(offset_ns (n,), period_ns (n,))``, tick k due at
    ``start + offset + k·period``. Aligned: zero offsets, 1 ms periods. Independent: offsets
    uniform in [0, 1 ms), periods 1 ms within ±RATE_SPREAD_PPM, from ``seed``."""
    if phases == "aligned":
        return np.zeros(n), np.full(n, float(PERIOD_NS))
    if phases != "independent":
        raise ValueError(f"phases must be one of {PHASES}, got {phases!r}")
    rng = np.random.default_rng(seed)
    offsets = rng.uniform(0.0, PERIOD_NS, n)
    periods = PERIOD_NS * (1.0 + rng.uniform(-1.0, 1.0, n) * RATE_SPREAD_PPM * 1e-6)
    return offsets, periods


def drive(streams: list[Stream], warmup_s: float, seconds: float, worker_pids: list[int],
          kernel_stamps: bool, read_per_tick: bool = True,
          clocks: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Run the schedules: ``warmup_s`` then ``seconds`` of ticks per session, then the drain.
    ``clocks``: each session's ``(offset_ns, period_ns)`` (:func:`station_clocks`; default
    aligned). Returns the generator's and the server's CPU over the
    measured window (from the first session's first measured tick to the last send), the
    send lateness, ns, and ``read``: "tick" if the window's replies were read once a
    session's tick (``read_per_tick``, where every warm-up reply carried the kernel's
    stamp), else "reply"."""
    warm = round(warmup_s * 1000)
    ticks = warm + round(seconds * 1000)
    for s in streams:
        s.send_ns = np.zeros(ticks, dtype=np.int64)
        s.seq0 = s.rules.seq
        _encode_all(s, ticks)
    n = len(streams)
    offsets, periods = clocks if clocks is not None else station_clocks(n, "aligned")
    late_ns = np.zeros((ticks, n), dtype=np.int64)
    sel = selectors.SelectSelector()  # epoll's timeout is whole ms: too coarse for 1 kHz
    for s in streams:
        sel.register(s.sock, selectors.EVENT_READ, s)
    clock = time.monotonic_ns
    realtime_minus_mono = time.time_ns() - clock()
    anc = socket.CMSG_SPACE(TIMESPEC.size) if kernel_stamps else 0

    def drain(s: Stream) -> None:
        while True:
            try:
                data, ancdata, _, _ = s.sock.recvmsg(RECV_BYTES, anc)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:  # an ICMP for an earlier datagram: keep going
                continue
            user = clock()
            kernel = 0
            for level, kind, value in ancdata:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    sec, nsec = TIMESPEC.unpack_from(value)
                    kernel = sec * 1_000_000_000 + nsec - realtime_minus_mono
            s.replies.append((kernel, user, data))

    gc.collect()
    gc.freeze()
    gc_was = gc.isenabled()
    gc.disable()
    # Every send of the run in the order it is due: (due ns from the start, session index,
    # tick), as plain lists (the loop's per-send cost is the generator's own load on the
    # server's cores). Built before the start is taken: 16 sessions are 176 000 sends.
    due_ns = np.rint(offsets[None, :]
                     + np.arange(ticks)[:, None] * periods[None, :]).astype(np.int64).ravel()
    order = np.argsort(due_ns, kind="stable")  # same instant: session order
    dues, sessions, tick_of = (due_ns[order].tolist(), (order % n).tolist(),
                               (order // n).tolist())
    del due_ns, order
    start = clock() + 20 * PERIOD_NS
    cpu0 = gen0 = wall0 = None
    report: dict = {"read": "reply"}
    per_tick = False
    with _generator_scheduling(report):
        try:
            e, events, now = 0, len(dues), clock()
            while e < events:
                due = start + dues[e]
                if now < due:
                    now = clock()
                if now >= due:
                    j, k = sessions[e], tick_of[e]
                    if k == warm and gen0 is None:
                        per_tick = read_per_tick and kernel_stamps and all(
                            s.replies and all(kernel for kernel, _, _ in s.replies)
                            for s in streams)
                        report["read"] = "tick" if per_tick else "reply"
                        cpu0 = [cpu_s(p) for p in worker_pids]
                        gen0, wall0 = time.thread_time_ns(), clock()
                    s = streams[j]
                    if per_tick:
                        drain(s)
                    t = clock()
                    try:
                        s.sock.send(s.datagrams[k])
                    except (ConnectionRefusedError, BlockingIOError):
                        pass  # counts as lost: no reply will come
                    s.send_ns[k] = t
                    late_ns[k, j] = t - due
                    now = t
                    e += 1
                    continue
                if per_tick:
                    # The kernel stamps each reply as it arrives: reading a session's replies
                    # just before its next send, in the wake-up that send needs anyway,
                    # changes no round trip and spares the server's cores a wake-up per
                    # reply (measured: 29 % of a core for 8 sessions when each reply woke
                    # the generator).
                    time.sleep((due - now) / 1e9)
                    continue
                for key, _ in sel.select((due - now) / 1e9):
                    drain(key.data)
            gen_ns, wall_ns = time.thread_time_ns() - gen0, clock() - wall0
            cpu1 = [cpu_s(p) for p in worker_pids]
            end = clock() + int(DRAIN_S * 1e9)
            while (now := clock()) < end:
                for key, _ in sel.select((end - now) / 1e9):
                    drain(key.data)
        finally:
            sel.close()
            if gc_was:
                gc.enable()
            gc.unfreeze()
    server_pct = None
    if None not in cpu0 and None not in cpu1:
        server_s = sum(b - a for a, b in zip(cpu0, cpu1, strict=True))
        server_pct = 100.0 * server_s * 1e9 / wall_ns
    return {"warm": warm, "late_ns": late_ns[warm:].ravel(), "wall_s": wall_ns / 1e9,
            "generator_cpu_pct": 100.0 * gen_ns / wall_ns, "server_cpu_pct": server_pct,
            **report}


def tally(streams: list[Stream], warm: int) -> dict:
    """Match replies to sends; round trips of the window's answered POSEs, µs."""
    rtt: list[np.ndarray] = []
    read: list[np.ndarray] = []
    sent = answered = cutting = kernel_used = stale = 0
    for s in streams:
        assert s.send_ns is not None
        ticks = len(s.send_ns)
        arrival = np.zeros(ticks, dtype=np.int64)
        read_ns = np.zeros(ticks, dtype=np.int64)
        kernel_stamped = np.zeros(ticks, dtype=bool)
        cut = np.zeros(ticks, dtype=bool)
        for kernel, user, data in s.replies:
            m = s.rules.accept(data, user // 1000)
            if m is None or isinstance(m, Notice) or m.reply.error != 0:
                continue
            i = (m.reply.seq - s.seq0) % SEQ_MODULUS
            if i >= ticks or arrival[i]:
                continue
            sent_ns = s.send_ns[i]
            # The kernel's stamp unless the clocks disagree (it cannot precede the send or
            # follow the read).
            kernel_stamped[i] = bool(kernel) and sent_ns <= kernel <= user
            arrival[i] = kernel if kernel_stamped[i] else user
            read_ns[i] = user
            cut[i] = bool(m.reply.status & STATUS_CUTTING)
        stale += s.rules.counters["stale"]
        window = slice(warm, ticks)
        got = arrival[window] > 0
        sent += int((s.send_ns[window] > 0).sum())
        answered += int(got.sum())
        cutting += int(cut[window][got].sum())
        kernel_used += int(kernel_stamped[window][got].sum())
        rtt.append((arrival[window][got] - s.send_ns[window][got]) / 1e3)
        read.append((read_ns[window][got] - s.send_ns[window][got]) / 1e3)
    all_rtt = np.concatenate(rtt) if rtt else np.zeros(0)
    p50, p99, p999 = percentiles(all_rtt, (50, 99, 99.9))
    r50, r99 = percentiles(np.concatenate(read) if read else np.zeros(0), (50, 99))
    return {"sent": sent, "answered": answered, "lost": sent - answered,
            "late": int((all_rtt > PERIOD_NS / 1e3).sum()),
            "rtt_p50_us": p50, "rtt_p99_us": p99, "rtt_p999_us": p999,
            "rtt_max_us": float(all_rtt.max()) if len(all_rtt) else None,
            # To the generator reading the reply: with kernel stamps it reads once a tick, so
            # this is up to a period later than the arrival and adds nothing to the round trip.
            "read_p50_us": r50, "read_p99_us": r99,
            "cutting_fraction": cutting / answered if answered else 0.0,
            "kernel_stamped_fraction": kernel_used / answered if answered else 0.0,
            "stale": stale}


