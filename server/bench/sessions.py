"""``burrforce bench sessions``: many concurrent cutting sessions at 1 kHz.

For each session count N: a fresh ``burrforce serve`` (``--workers W`` when given), N sessions
each on its own 0.1 mm workpiece (so their grooves never meet), each cutting bench latency's
groove raster (α = 60°, 0.5 mm deep, 3 mm/s, 60 000 rpm) through the real protocol: hello →
NEW_STREAM → keyed POSEs (``client.udp.SessionRules``: codec, tag, stream).

One load generator (this process, one thread) sends each session's POSEs on that session's
own 1 kHz schedule; nothing spins, so the generator does not take a core per session. By
default (``--phases aligned``) every session's POSE is due at the same instant each tick, the
worst case, where each worker meets its sessions' packets in one burst. Stations are
independent machines, though: with ``--phases independent`` each session's clock has its own
phase (uniform in the period) and its own rate (within ±50 ppm, so the phases slide over each
other during the run and every relative alignment is visited). The POSEs are encoded and
signed before the schedule starts, so during it the generator only sends and receives.
Between sends it either sleeps and reads a session's replies just before that session's next
send (``--read tick``, the default), or sleeps in ``select`` and reads each reply as it comes
(``--read reply``: a wake-up per reply, on the cores the server uses). Reading at the next
send changes no round trip, which is taken from the kernel's arrival stamp, so it is used only
if the warm-up's replies all carried one; otherwise the run reads per reply and says so. Its
own cost is reported (its thread's CPU % over the window and how late its sends were against
the schedule) so that generator overload can be told from server overload. While it drives,
it runs at the hot loop's raised priority where it may (the loop raises its own: a saturated
loop would otherwise starve the generator on a small machine), and under SCHED_FIFO above
the loops where allowed, with or without ``--realtime``: it stands for stations on other
machines, whose sends the server's load does not delay.

Definitions (per N, over the measured window, after the warm-up):

- round trip: from the send stamp (``time.monotonic_ns`` just before ``send``) to the
  reply's arrival on the generator's socket, stamped by the
  kernel (``SO_TIMESTAMPNS``, so a generator busy sending does not inflate it; the user-space
  read time when the kernel gives none, which only reading per reply allows);
- lost: POSEs sent in the window − replies to them received by the end of a drain period;
- late: answered POSEs whose round trip exceeded the 1 ms haptic period (the reply missed the
  next tick); lost ones are counted apart;
- send lateness: a POSE's send stamp − its tick's deadline (the generator's own lag);
- server CPU: utime + stime of the hot-loop worker process(es) (``/proc/PID/stat``) over the
  window, as % of one core, in total and divided by N.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import os
import selectors
import socket
import struct
import tempfile
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...client.udp import SessionRules
from ...proto.messages import HELLO_STREAM, NEW_STREAM, SEQ_MODULUS, STATUS_CUTTING, Notice
from ..argtypes import float_in, int_at_least
from . import runner
from .latency import ALPHA_DEG, DEPTH_MM, FEED_MM_S, HELLO_TRIES, RPM, GrooveCut
from .procstat import cpu_s
from .serve_process import spawn_serve
from .soak import Rest

DEFAULT_SESSIONS = (1, 2, 4, 8, 16)
VOXEL_MM = 0.1
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
TARGET = ("8 cutting sessions at 1 kHz: p99 < 1 ms and 0 lost; cost per session linear until "
          "the cores are busy")


@dataclass
class _Stream:
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


def _kernel_timestamps(sock: socket.socket) -> bool:
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def _open(host: str, port: int, session: int, key_hex: str | None,
          worker: int | None) -> _Stream:
    sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect((host, port))
    # Seconds of replies fit, should the generator fall behind for a while.
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    return _Stream(session, worker, sock, SessionRules(session, key_hex, 1))


def _handshake(s: _Stream) -> None:
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


def _percentiles(values: np.ndarray, qs: tuple[float, ...]) -> list[float | None]:
    if len(values) == 0:
        return [None for _ in qs]
    return [float(v) for v in np.percentile(values, qs)]


def _encode_all(s: _Stream, ticks: int) -> None:
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


def drive(streams: list[_Stream], warmup_s: float, seconds: float, worker_pids: list[int],
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

    def drain(s: _Stream) -> None:
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


def tally(streams: list[_Stream], warm: int) -> dict:
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
    p50, p99, p999 = _percentiles(all_rtt, (50, 99, 99.9))
    r50, r99 = _percentiles(np.concatenate(read) if read else np.zeros(0), (50, 99))
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


def _health(url: str) -> dict:
    """GET /v1/health, also when it answers 503 (a worker down or being restarted)."""
    try:
        with urllib.request.urlopen(url + "/v1/health", timeout=30) as r:
            return json.loads(r.read())
    except urllib.error.HTTPError as exc:
        if exc.code != 503:
            raise
        return json.loads(exc.read())


def _worker_pids(health: dict) -> list[int]:
    """The hot-loop worker processes: ``workers[].pid`` (a pool), else ``supervisor.pid``."""
    pids = [w["pid"] for w in health.get("workers") or () if w.get("pid")]
    if not pids and (health.get("supervisor") or {}).get("pid"):
        pids = [health["supervisor"]["pid"]]
    if not pids:
        raise RuntimeError(f"the server names no hot-loop process: {health}")
    return pids


def run_one(n: int, workers: int | None, warmup_s: float, seconds: float, read: str = "tick",
            progress=lambda text: None, wake_ahead_us: float | None = None,
            phases: str = "aligned", seed: int = 1, realtime: bool = False) -> dict:
    """One session count on a fresh ``burrforce serve``: a row of the results. ``phases``
    and ``seed``: the sessions' clocks (:func:`station_clocks`); ``realtime``: ``serve
    --realtime``."""
    clocks = station_clocks(n, phases, seed)
    extra = ["--workers", str(workers)] if workers is not None else []
    if realtime:
        extra.append("--realtime")
    if wake_ahead_us is not None:
        extra += ["--wake-ahead-us", f"{wake_ahead_us:g}"]
    with tempfile.TemporaryDirectory(prefix="burrforce-bench-sessions-") as tmp:
        progress(f"N = {n}: starting burrforce serve {' '.join(extra)}".rstrip())
        serve = spawn_serve(Path(tmp), "--bone", "phantom:workpiece", "--voxel-mm",
                            str(VOXEL_MM), *extra)
        streams: list[_Stream] = []
        try:
            c = serve.connection
            rest = Rest(c.http_url, c.token)
            view = json.loads(rest("GET", f"/v1/sessions/{c.session}"))
            streams.append(_open(c.host, c.udp_port, c.session, c.key_hex, view.get("worker")))
            for i in range(n - 1):
                progress(f"N = {n}: loading session {i + 2}/{n}'s workpiece")
                made = json.loads(rest("POST", "/v1/sessions", {
                    "bone": {"source": "phantom:workpiece", "voxel_mm": VOXEL_MM}}))
                if made.get("state") != "ready":
                    raise RuntimeError(f"session {made.get('id')} is {made.get('state')}: "
                                       f"{made.get('error')}")
                udp = made.get("udp") or {}  # a single loop: the connection's endpoint
                streams.append(_open(udp.get("host") or c.host, udp.get("port") or c.udp_port,
                                     made["id"], made["key"], made.get("worker")))
            health = _health(c.http_url)
            pids = _worker_pids(health)
            stamps = all([_kernel_timestamps(s.sock) for s in streams])
            for s in streams:
                _handshake(s)
            progress(f"N = {n}: {warmup_s:g} s warm-up, {seconds:g} s measured")
            timing = drive(streams, warmup_s, seconds, pids, stamps, read == "tick", clocks)
            health = _health(c.http_url)
        finally:
            for s in streams:
                s.sock.close()
            serve.stop()
    row = {"sessions": n, "workers": len(pids), "worker_pids": pids, "phases": phases,
           "realtime_workers": sum(bool(w.get("realtime")) for w in health.get("workers") or ())}
    row |= tally(streams, timing["warm"])
    late_us = timing["late_ns"] / 1e3
    s50, s99 = _percentiles(late_us, (50, 99))
    row |= {
        "late_pct": 100.0 * row["late"] / row["answered"] if row["answered"] else None,
        "send_late_p50_us": s50, "send_late_p99_us": s99,
        "send_late_max_us": float(late_us.max()) if len(late_us) else None,
        "generator_cpu_pct": timing["generator_cpu_pct"],
        "generator_nice": timing["generator_nice"],
        "generator_realtime": timing["generator_realtime"],
        "read": timing["read"],
        "server_cpu_pct": timing["server_cpu_pct"],
        "server_cpu_per_session_pct": None if timing["server_cpu_pct"] is None
        else timing["server_cpu_pct"] / n,
        "window_s": timing["wall_s"],
        "sessions_per_worker": [w.get("sessions") for w in health.get("workers") or ()]
        or [n],
        "restarts": (health.get("supervisor") or {}).get("restarts"),
        "health_after": health.get("status"),
    }
    return row


def run(counts: list[int], workers: int | None, warmup_s: float, seconds: float,
        progress=lambda text: None, read: str = "tick",
        wake_ahead_us: float | None = None, phases: str = "aligned",
        seed: int = 1, realtime: bool = False) -> dict:
    rows = []
    for n in counts:
        rows.append(run_one(n, workers, warmup_s, seconds, read, progress, wake_ahead_us,
                            phases, seed, realtime))
        r = rows[-1]
        progress(f"N = {n}: p50 {r['rtt_p50_us'] or 0:.0f} µs, p99 {r['rtt_p99_us'] or 0:.0f} "
                 f"µs, lost {r['lost']}/{r['sent']}, generator {r['generator_cpu_pct']:.0f} %")
    return {"voxel_mm": VOXEL_MM, "warmup_s": warmup_s, "seconds": seconds,
            "workers_option": workers, "read_option": read,
            "wake_ahead_us_option": wake_ahead_us, "realtime_option": realtime,
            "phases_option": phases,
            "phase_seed": seed, "rate_spread_ppm": RATE_SPREAD_PPM, "rows": rows}


def _f(value: float | None, fmt: str = ".0f") -> str:
    return "–" if value is None else format(value, fmt)


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, js = runner.save_json(out, "sessions", result | {"target": TARGET}, utc=True)
    stamp = result["date"]
    workers = result["workers_option"]
    lines = [
        "# Concurrent cutting sessions at 1 kHz (`burrforce bench sessions`)", "",
        f"{stamp}; {result['machine']}. Per session count N: a fresh `burrforce serve` "
        f"({'--workers ' + str(workers) if workers else 'its default workers'}"
        + (f", --wake-ahead-us {result['wake_ahead_us_option']:g}"
           if result.get("wake_ahead_us_option") is not None else "")
        + (", --realtime" if result.get("realtime_option") else "")
        + "), N sessions "
        f"each on its own workpiece at {result['voxel_mm']:g} mm voxels, cutting at "
        f"α = {ALPHA_DEG:g}°, {DEPTH_MM:g} mm deep, {FEED_MM_S:g} mm/s, {RPM:g} rpm, keyed "
        "POSEs at 1 kHz from one single-threaded load generator (all encoded and signed "
        "before the run; "
        + ("it wakes for each session's tick, reads that session's replies the kernel has "
           "stamped and sends its POSE" if result.get("read_option", "tick") == "tick" else
           "it wakes for each reply, `--read reply`")
        + "). "
        + (f"Sessions' clocks independent (`--phases independent`, seed "
           f"{result.get('phase_seed')}): each its own phase in the 1 ms period and its own "
           f"rate within ±{RATE_SPREAD_PPM:g} ppm, so their phases slide over each other "
           "during the run" if result.get("phases_option") == "independent" else
           "Sessions' clocks aligned (`--phases aligned`): every session's POSE is due at "
           "the same instant, the worst case")
        + "; "
        f"{result['warmup_s']:g} s warm-up, then {result['seconds']:g} s measured.", "",
        "Round trip: send stamp → the reply's kernel arrival stamp. Lost: sent in the window "
        f"− answered after a {DRAIN_S:g} s drain. Late: answered with a round trip > 1 ms "
        "(missed the next haptic tick; lost ones apart). Send lateness: the generator's send "
        "stamp − the tick's deadline. Server CPU: utime + stime of the hot-loop worker "
        "process(es) over the window, % of one core.", "",
        f"Target: {TARGET}.", "",
    ]
    for r in result["rows"]:
        lines += [
            f"## N = {r['sessions']} ({r['workers']} worker{'s' if r['workers'] != 1 else ''}"
            f", sessions per worker {r['sessions_per_worker']}, clocks {r['phases']})", "",
            "| measure | value |", "|---|---:|",
            f"| POSEs sent / answered / lost | {r['sent']} / {r['answered']} / {r['lost']} |",
            f"| round trip p50 / p99 / p99.9 / max µs | {_f(r['rtt_p50_us'])} / "
            f"{_f(r['rtt_p99_us'])} / {_f(r['rtt_p999_us'])} / {_f(r['rtt_max_us'])} |",
            f"| replies read | {'once a tick' if r.get('read') == 'tick' else 'per reply'} |",
            f"| generator's read of the reply p50 / p99 µs (at the next deadline when read "
            f"once a tick) | "
            f"{_f(r['read_p50_us'])} / {_f(r['read_p99_us'])} |",
            f"| late replies (> 1 ms) | {r['late']} ({_f(r['late_pct'], '.2f')} %) |",
            f"| replies while cutting | {100 * r['cutting_fraction']:.0f} % |",
            f"| server CPU total / per session | {_f(r['server_cpu_pct'])} % / "
            f"{_f(r['server_cpu_per_session_pct'], '.1f')} % |",
            f"| worker restarts / health after the run | {r['restarts']} / "
            f"{r['health_after']} |",
            f"| loops under SCHED_FIFO | {r['realtime_workers']} of {r['workers']} |",
            f"| generator CPU (at nice {r['generator_nice']}"
            f"{', SCHED_FIFO' if r['generator_realtime'] else ''}) | "
            f"{r['generator_cpu_pct']:.0f} % |",
            f"| generator send lateness p50 / p99 / max µs | {_f(r['send_late_p50_us'])} / "
            f"{_f(r['send_late_p99_us'])} / {_f(r['send_late_max_us'])} |",
            "",
        ]
    lines += [
        "| N | workers | p50 µs | p99 µs | p99.9 µs | lost | late | server CPU/session % "
        "| generator CPU % | send late p99 µs |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['sessions']} | {r['workers']} | {_f(r['rtt_p50_us'])} | "
            f"{_f(r['rtt_p99_us'])} | {_f(r['rtt_p999_us'])} | {r['lost']} | {r['late']} | "
            f"{_f(r['server_cpu_per_session_pct'], '.1f')} | {r['generator_cpu_pct']:.0f} | "
            f"{_f(r['send_late_p99_us'])} |")
    md = out / "sessions.md"
    md.write_text("\n".join(lines) + "\n")
    return md, js


def _counts(text: str) -> list[int]:
    try:
        values = [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"session counts must be comma-separated integers, got {text!r}") from None
    if not values or any(not 1 <= v <= 256 for v in values):
        raise argparse.ArgumentTypeError(f"each session count must be in 1..256, got {text!r}")
    return values


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "sessions", main,
        help="many concurrent cutting sessions at 1 kHz from one load generator",
        description="For each session count: a fresh `burrforce serve`, that many sessions "
                    "each cutting its own 0.1 mm workpiece at 1 kHz, driven by one "
                    "single-threaded load generator. Reports round trips, lost and late "
                    "replies, server CPU per session and the generator's own cost. Writes "
                    "OUT/sessions.md and sessions.json.", json_help=runner.JSON_ROWS)
    p.add_argument("--sessions", type=_counts, default=list(DEFAULT_SESSIONS),
                   help="session counts, comma-separated. Default 1,2,4,8,16")
    p.add_argument("--workers", type=int_at_least(1, "--workers"), default=None,
                   help="passed to `burrforce serve --workers`. Default: serve's default")
    p.add_argument("--wake-ahead-us", type=float_in(0.0, 5000.0, "--wake-ahead-us", "µs"),
                   default=None, metavar="US",
                   help="passed to `burrforce serve --wake-ahead-us` (0: the loops block "
                        "until each datagram). Default: serve's default")
    p.add_argument("--seconds", type=float_in(0.1, 3600.0, "measured window", "s"),
                   default=10.0, help="measured window per session count, s. Default 10")
    p.add_argument("--warmup-s", type=float_in(0.0, 600.0, "warm-up", "s"), default=1.0,
                   help="streamed before the window, not measured, s. Default 1")
    p.add_argument("--read", choices=("tick", "reply"), default="tick",
                   help="read the replies once a tick, by the kernel's arrival stamps (the "
                        "default; per reply where the kernel gives none), or per reply as "
                        "each arrives (a wake-up per reply)")
    p.add_argument("--realtime", action="store_true",
                   help="`burrforce serve --realtime` (the loops under SCHED_FIFO where "
                        "allowed; the generator is, above them, either way)")
    p.add_argument("--phases", choices=PHASES, default="aligned",
                   help="the sessions' clocks: aligned, every POSE of a tick sent at the "
                        "same instant (the worst case, the default), or independent "
                        "stations, each its own phase and a rate within "
                        f"±{RATE_SPREAD_PPM:g} ppm")
    p.add_argument("--phase-seed", type=int, default=1, metavar="SEED",
                   help="the independent clocks' random seed. Default 1")


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    result = run(args.sessions, args.workers, args.warmup_s, args.seconds, runner.say,
                 args.read, args.wake_ahead_us, args.phases, args.phase_seed, args.realtime)
    md, js = write_results(result, out)
    return runner.report(args, md, js, rows=result["rows"])
