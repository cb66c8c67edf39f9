"""``burrforce bench latency``: round trips through the real protocol against a bare UDP echo.

Three servers on this machine's loopback, measured in one run with their samples interleaved
in chunks (this machine is shared: slow spells then fall on every run alike):

- ``echo``: a bare Python UDP echo (``bench.echo``) — the floor: two processes, two sockets,
  four system calls and two wake-ups;
- ``overhead``: the hot loop with the model stage skipped — decode, tag check, sequence,
  frames, encode, sign: the protocol's own cost;
- ``cutting``: the hot loop cutting the thesis's workpiece (0.1 mm voxels, α = 60°,
  0.5 mm deep, 3 mm/s, 60 000 rpm) along a raster of grooves, with every scene feature on, as
  ``burrforce serve`` runs it (a shared-memory bone published to the control plane, the
  shaft, vibration, waking ahead of the stream's packets: ``hotloop.wake``);
- ``blocking``: the same cut on its own copy of the bone, in a second hot loop that does not
  wake ahead (``serve --wake-ahead-us 0``): it sleeps in ``epoll_wait`` until each datagram,
  as the echo does;
- ``realtime``: the same cut on its own copy of the bone, in a hot loop of its own started as
  ``serve --realtime`` does (SCHED_FIFO, blocking for each datagram; where that is not
  permitted it runs as ``blocking``, and the results say so);
- ``minimal``: the same cut on its own copy of the bone with the scene features a bare
  cutting scene can drop turned off (no shaft, no vibration, no publishing): what skipping
  them saves;
- ``watched``: the same cut as ``cutting`` on its own copy of the bone, while another
  process samples its telemetry at 60 Hz and encodes each sample as the WebSocket does
  (``bench.telemetry_watch``, paused during every other run's chunks): what a live view
  costs. Both keep their per-packet state in a telemetry file, as under ``serve``;
- ``hogged`` / ``hogged blocking`` / ``hogged realtime``: the same cut, each on its own copy
  of the bone in a hot loop of its own (one that wakes ahead, one that does not, one under
  SCHED_FIFO), while a CPU-bound task (a busy
  Python loop, ``HOG``) runs on the servers' CPU, stopped during every other run's chunks: an
  engine thread sharing the hot loop's core. A loop that polls would wait for that task's time
  slice; the waking-ahead guard (``hotloop.wake``) notices and stops polling. Their own loops
  keep the guard's back-off out of the other modes;
- ``page closed`` / ``page open``: the browser view itself, open and closed on a cutting
  session of the real stack: the project's own measurement (headless Chromium driven by
  playwright), run from a checkout as ``python -m benchmarks.latency``
  (``benchmarks/latency_page.py``; ``--no-page`` skips it there). This command leaves it out
  and says so in the results.

Each paced at 1 kHz (the haptic rate; sends on an absolute schedule) and back-to-back. A
round trip runs from the client stamping its packet (before encoding, as a real client) to
the reply's arrival (before decoding).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ...proto.codec import decode_server_message, encode_pose
from ...proto.messages import FLAG_RESET_VELOCITY, NEW_STREAM, STATUS_CUTTING, Notice, Pose
from ...proto.tag import Tagger, new_key
from ..argtypes import float_in, int_in
from . import runner
from .timing import wait_until

MODES = ("echo", "overhead", "cutting", "blocking", "realtime", "watched", "minimal", "hogged",
         "hogged blocking", "hogged realtime")
#: The modes whose round trips are taken over the ticks that removed bone.
CUTTING_MODES = ("cutting", "blocking", "realtime", "watched", "minimal", "hogged",
                 "hogged blocking", "hogged realtime")
#: The modes that run the CPU-bound task beside their loop.
HOGGED_MODES = ("hogged", "hogged blocking", "hogged realtime")
#: The CPU-bound task of the ``hogged`` modes: never blocks, never yields, and dies with the
#: bench (Linux's parent-death signal, PR_SET_PDEATHSIG = 1), however the bench ends.
#: Its argument: the bench's pid (a bench that died before the signal was set is noticed).
HOG = ("import ctypes, os, signal, sys\n"
       "ctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"
       "if os.getppid() == int(sys.argv[1]):\n"
       "    while True:\n        pass\n")
#: A live view's sampling rate (the browser view's plots: >= 30 updates/s).
WATCH_HZ = 60.0
OVERHEAD_SESSION = 1
CUTTING_SESSION = 2
MINIMAL_SESSION = 3
WATCHED_SESSION = 4
BLOCKING_SESSION = 5
HOGGED_SESSION = 6
HOGGED_BLOCKING_SESSION = 7
REALTIME_SESSION = 8
HOGGED_REALTIME_SESSION = 9
#: The cut: the thesis's parallel case at α = 60°, rows across the 26 × 16 mm top face.
RPM = 60_000.0
FEED_MM_S = 3.0
DEPTH_MM = 0.5
RADIUS_MM = 2.0
ALPHA_DEG = 60.0
ROWS_Y_MM = (-6.0, -2.0, 2.0, 6.0)
ROW_X_MM = (-2.5, 28.5)  # from outside the block (x 0–26) to outside it again
REPLY_TIMEOUT_S = 0.25
CHUNK = 500
#: Hellos sent (each waits REPLY_TIMEOUT_S) before the server counts as not answering.
HELLO_TRIES = 8


@dataclass(frozen=True)
class RunStats:
    mode: str
    pacing: str
    samples: int
    lost: int
    p50_us: float
    p99_us: float
    p999_us: float
    max_us: float
    cutting_fraction: float | None = None

    def quantiles(self, prefix: str, which: Sequence[str] = ("p50", "p99")) -> dict[str, float]:
        """The result's fields for this run: ``PREFIXp50_us`` and so on, µs."""
        return {f"{prefix}{q}_us": getattr(self, f"{q}_us") for q in which}


def run_stats(mode: str, pacing: str, rtt_us: np.ndarray, lost: int,
              cutting_fraction: float | None = None) -> RunStats:
    if len(rtt_us) == 0:
        nan = float("nan")
        return RunStats(mode, pacing, 0, lost, nan, nan, nan, nan, cutting_fraction)
    return RunStats(mode, pacing, len(rtt_us), lost, float(np.median(rtt_us)),
                    float(np.percentile(rtt_us, 99)), float(np.percentile(rtt_us, 99.9)),
                    float(rtt_us.max()), cutting_fraction)


class GrooveCut:
    """Poses along the raster, advanced by the client's own clock so the feed speed is 3 mm/s
    whatever the pacing. Past the last row it starts again 0.5 mm deeper."""

    def __init__(self) -> None:
        beta = math.radians(ALPHA_DEG - 90.0)  # tilt +z back against the feed, about y
        self.orientation = (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))
        self.path_s = 0.0
        self.last_us: int | None = None
        self.row = -1

    def pose(self, t_us: int, new_chunk: bool) -> tuple[tuple[float, float, float], int]:
        if self.last_us is not None:
            self.path_s += 0.001 if new_chunk else (t_us - self.last_us) * 1e-6
        self.last_us = t_us
        row_s = (ROW_X_MM[1] - ROW_X_MM[0]) / FEED_MM_S
        k = int(self.path_s // row_s)
        flags = FLAG_RESET_VELOCITY if k != self.row else 0
        self.row = k
        y = ROWS_Y_MM[k % len(ROWS_Y_MM)]
        z = RADIUS_MM - DEPTH_MM * (1 + k // len(ROWS_Y_MM))
        x = ROW_X_MM[0] + FEED_MM_S * (self.path_s - k * row_s)
        return (x, y, z), flags


class StreamClient:
    """A lean client: stamp, encode, send, block on the reply, stamp its arrival."""

    def __init__(self, address: tuple[str, int], session: int | None, key: bytes | None,
                 cut: GrooveCut | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.connect(address)
        self.sock.settimeout(REPLY_TIMEOUT_S)
        self.session = session
        self.tagger = Tagger(key) if key is not None else None
        self.cut = cut
        self.seq = 1
        self.stream = 0  # the server's stream for this client (SPEC 5.2), 0 before the hello
        self.echo_payload = bytes(110)  # the size of a POSE
        self.rtt_us: list[float] = []
        self.cutting: list[bool] = []
        self.lost = 0

    def _open_stream(self) -> None:
        """The stream handshake, untimed: a hello, the server's NEW_STREAM notice."""
        for _ in range(HELLO_TRIES):
            seq = self.seq
            self.seq += 1
            hello = Pose(self.session, seq, time.monotonic_ns() // 1000, (12.0, 0.0, 20.0),  # type: ignore[arg-type]
                         (0.0, 0.0, 0.0, 1.0), RPM, True)
            self.sock.send(encode_pose(hello, self.tagger))
            try:
                while True:
                    data = self.sock.recv(2048)
                    m = decode_server_message(data)
                    if (isinstance(m, Notice) and m.error == NEW_STREAM and m.seq == seq
                            and (self.tagger is None or self.tagger.verify(data))):
                        self.stream = m.stream
                        return
            except TimeoutError:
                continue
        raise RuntimeError(f"session {self.session} never answered a hello")

    def chunk(self, n: int, period_s: float | None) -> None:
        if self.session is not None and self.stream == 0:
            self._open_stream()
        clock = time.monotonic_ns
        due = time.perf_counter()
        for i in range(n):
            if period_s is not None:
                due += period_s
                wait_until(due)
            t0 = clock()
            if self.session is None:
                self.sock.send(self.echo_payload)
            else:
                self.sock.send(self.datagram(t0 // 1000, i == 0))
            try:
                data = self.sock.recv(2048)
                t1 = clock()  # the arrival: decoding the reply is the client's own time
                while self.session is not None and not self.is_reply(data):
                    data = self.sock.recv(2048)
                    t1 = clock()
            except TimeoutError:
                self.lost += 1
                continue
            self.rtt_us.append((t1 - t0) / 1e3)
            if self.cut is not None:
                self.cutting.append(bool(decode_server_message(data).status & STATUS_CUTTING))

    def datagram(self, t_us: int, new_chunk: bool) -> bytes:
        seq = self.seq
        self.seq += 1
        flags = 0
        if self.cut is None:
            position = (12.0, 0.0, 20.0)
            orientation = (0.0, 0.0, 0.0, 1.0)
        else:
            position, extra = self.cut.pose(t_us, new_chunk)
            flags |= extra
            orientation = self.cut.orientation
        return encode_pose(Pose(self.session, seq, t_us, position, orientation, RPM, True,  # type: ignore[arg-type]
                                None, flags, self.stream), self.tagger)

    def is_reply(self, data: bytes) -> bool:
        """The reply to the packet just sent (a late one from a timed-out packet is not)."""
        return decode_server_message(data).seq == self.seq - 1


def pin_cpus(*server_pids: int) -> str:
    """Servers on the last CPU, this client on the first: the same placement for the echo
    and the hot loop. Left to the scheduler, a round trip between two processes costs a
    context switch when both land on one CPU and a cross-CPU wake-up (~3× slower in a VM)
    when they do not, and runs differ by that alone."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return "not pinned (one CPU)"
    try:
        for pid in server_pids:
            os.sched_setaffinity(pid, {cpus[-1]})
        os.sched_setaffinity(0, {cpus[0]})
    except OSError as exc:
        return f"not pinned ({exc.strerror})"
    return f"servers on CPU {cpus[-1]}, client on CPU {cpus[0]}"


def run(samples_paced: int, samples_b2b: int, voxel_mm: float, rate_hz: float = 1000.0,
        progress=None) -> dict:
    import shutil

    from ..api.telemetry import TelemetryReader
    from ..bone import ShaftParams, phantom
    from ..bone.shared import publish, run_directory
    from ..hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec
    from ..hotloop.wake import WakeConfig
    from ..realtime import is_realtime

    say = progress or (lambda text: None)
    key = new_key()
    bone = phantom("workpiece", voxel_mm)
    shared = run_directory(3 * bone.grid.density.size * 7)
    telemetry = TelemetryReader(shared)
    sessions = (
        SessionSpec(OVERHEAD_SESSION, "phantom:workpiece", 0.5, key,
                    SessionConfig(model=False)),
        SessionSpec(CUTTING_SESSION, publish(bone, shared, "full.bone"), None, key,
                    SessionConfig(), publish=True, telemetry=telemetry.path(CUTTING_SESSION)),
        SessionSpec(WATCHED_SESSION, publish(bone, shared, "watched.bone"), None, key,
                    SessionConfig(), publish=True, telemetry=telemetry.path(WATCHED_SESSION)),
        SessionSpec(MINIMAL_SESSION, publish(bone, shared, "minimal.bone"), None, key,
                    SessionConfig(vibration=None), shaft=ShaftParams(length_mm=0.0),
                    publish=False),
    )
    blocking_spec = SessionSpec(BLOCKING_SESSION, publish(bone, shared, "blocking.bone"), None,
                                key, SessionConfig(), publish=True,
                                telemetry=telemetry.path(BLOCKING_SESSION))
    # The modes with a loop of their own: its session (on its own copy of the bone), its
    # wake setting and whether it asks for SCHED_FIFO (``serve --realtime``).
    own_loops = {
        mode: (SessionSpec(session, publish(bone, shared, f"{mode.replace(' ', '-')}.bone"),
                           None, key, SessionConfig(), publish=True,
                           telemetry=telemetry.path(session)), wake, realtime)
        for mode, session, wake, realtime in (
            ("realtime", REALTIME_SESSION, WakeConfig(), True),
            ("hogged", HOGGED_SESSION, WakeConfig(), False),
            ("hogged blocking", HOGGED_BLOCKING_SESSION, WakeConfig(lead_us=0.0), False),
            ("hogged realtime", HOGGED_REALTIME_SESSION, WakeConfig(), True))}
    del bone
    say("starting the echo and the hot loops (warm-up compiles or loads the kernels)")
    echo = subprocess.Popen([sys.executable, "-m", "burrforce.server.bench.echo"],
                            stdout=subprocess.PIPE, text=True)
    hot = HotLoopProcess(HotLoopConfig(sessions=sessions))
    blocking = HotLoopProcess(HotLoopConfig(sessions=(blocking_spec,),
                                            wake=WakeConfig(lead_us=0.0)))
    own = {mode: HotLoopProcess(HotLoopConfig(sessions=(spec,), wake=wake, realtime=realtime))
           for mode, (spec, wake, realtime) in own_loops.items()}
    watcher = None
    hog = None
    cpus = os.sched_getaffinity(0)  # pin_cpus pins this process; the caller gets its CPUs back
    try:
        echo_port = int(echo.stdout.readline())  # type: ignore[union-attr]
        address = hot.start()
        blocking_address = blocking.start()
        own_address = {mode: loop.start() for mode, loop in own.items()}
        hog = subprocess.Popen([sys.executable, "-c", HOG, str(os.getpid())])
        hog.send_signal(signal.SIGSTOP)
        placement = pin_cpus(hot.pid, blocking.pid, echo.pid, hog.pid,
                         *(loop.pid for loop in own.values()))
        watcher = subprocess.Popen([sys.executable, "-m", "burrforce.server.bench.telemetry_watch",
                                    str(shared), str(WATCHED_SESSION), str(WATCH_HZ)],
                                   stdout=subprocess.PIPE, text=True)
        watcher.stdout.readline()  # type: ignore[union-attr]
        watcher.send_signal(signal.SIGSTOP)
        clients = {
            "echo": StreamClient(("127.0.0.1", echo_port), None, None),
            "overhead": StreamClient(address, OVERHEAD_SESSION, key),
            "cutting": StreamClient(address, CUTTING_SESSION, key, GrooveCut()),
            "blocking": StreamClient(blocking_address, BLOCKING_SESSION, key, GrooveCut()),
            "watched": StreamClient(address, WATCHED_SESSION, key, GrooveCut()),
            "minimal": StreamClient(address, MINIMAL_SESSION, key, GrooveCut()),
        } | {mode: StreamClient(own_address[mode], spec.session_id, key, GrooveCut())
             for mode, (spec, _, _) in own_loops.items()}
        realtime_granted = {mode: is_realtime(own[mode].pid)
                            for mode in ("realtime", "hogged realtime")}
        results: list[RunStats] = []
        # The client's own collector must not show up as server latency: a full collection
        # in a process that imported numba takes ~30 ms. Frozen objects are never walked.
        gc.collect()
        gc.freeze()
        for pacing, total, period in (("1 kHz", samples_paced, 1.0 / rate_hz),
                                      ("back-to-back", samples_b2b, None)):
            for c in clients.values():
                c.rtt_us, c.cutting, c.lost = [], [], 0
            done = 0
            while done < total:
                n = min(CHUNK, total - done)
                for mode in MODES:
                    beside = watcher if mode == "watched" else hog if mode in HOGGED_MODES \
                        else None
                    if beside is not None:
                        beside.send_signal(signal.SIGCONT)
                    clients[mode].chunk(n, period)
                    if beside is not None:
                        beside.send_signal(signal.SIGSTOP)
                done += n
                say(f"{pacing}: {done}/{total}")
            for mode in MODES:
                c = clients[mode]
                rtt = np.array(c.rtt_us)
                fraction = None
                if mode in CUTTING_MODES:
                    mask = np.array(c.cutting, dtype=bool)
                    fraction = float(mask.mean()) if len(mask) else 0.0
                    rtt = rtt[mask]  # the expensive ticks: the burr removing bone
                results.append(run_stats(mode, pacing, rtt, c.lost, fraction))
        server = hot.stats()
        server_blocking = blocking.stats()
        server_hogged = own["hogged"].stats()
        echo.stdout.close()  # type: ignore[union-attr]
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM).sendto(b"stop",
                                                                ("127.0.0.1", echo_port))
    finally:
        gc.unfreeze()
        os.sched_setaffinity(0, cpus)
        if hog is not None:
            hog.kill()
            hog.wait()
        watched_samples = ""
        if watcher is not None:
            watcher.send_signal(signal.SIGCONT)
            watcher.terminate()
            try:
                watched_samples = (watcher.communicate(timeout=10)[0] or "").strip()
            except subprocess.TimeoutExpired:
                watcher.kill()
                watcher.communicate()
        hot.stop()
        blocking.stop()
        for loop in own.values():
            loop.stop()
        shutil.rmtree(shared, ignore_errors=True)
        try:
            echo.wait(2.0)
        except subprocess.TimeoutExpired:
            echo.kill()
    cutting = server["sessions"][CUTTING_SESSION]
    minimal = server["sessions"][MINIMAL_SESSION]
    watched = server["sessions"][WATCHED_SESSION]
    paced = {r.mode: r for r in results if r.pacing == "1 kHz"}
    b2b = {r.mode: r for r in results if r.pacing == "back-to-back"}
    return {
        **paced["echo"].quantiles("echo_"),
        **paced["overhead"].quantiles("overhead_"),
        **paced["cutting"].quantiles("", ("p50", "p99", "p999")),
        "b2b_echo_p50_us": b2b["echo"].p50_us,
        "b2b_overhead_p50_us": b2b["overhead"].p50_us,
        **b2b["cutting"].quantiles("b2b_"),
        "server_tick_p50_us": cutting["tick_p50_us"],
        "server_tick_p99_us": cutting["tick_p99_us"],
        **paced["blocking"].quantiles("blocking_"),
        "b2b_blocking_p50_us": b2b["blocking"].p50_us,
        "server_tick_blocking_p50_us":
            server_blocking["sessions"][BLOCKING_SESSION]["tick_p50_us"],
        **paced["watched"].quantiles("watched_"),
        "watch_hz": WATCH_HZ,
        "server_tick_watched_p50_us": watched["tick_p50_us"],
        "watched_samples": int(watched_samples) if watched_samples.isdigit() else None,
        **paced["minimal"].quantiles("minimal_"),
        "server_tick_minimal_p50_us": minimal["tick_p50_us"],
        "server_tick_minimal_p99_us": minimal["tick_p99_us"],
        **paced["hogged"].quantiles("hogged_"),
        **paced["hogged blocking"].quantiles("hogged_blocking_"),
        **paced["realtime"].quantiles("realtime_"),
        **paced["hogged realtime"].quantiles("hogged_realtime_"),
        "realtime_granted": realtime_granted,
        "hogged_wake_counters": {name: value for name, value
                                 in server_hogged["counters"].items()
                                 if name.startswith("wake_")},
        "voxel_mm": voxel_mm,
        "placement": placement,
        "rate_hz": rate_hz,
        "runs": [asdict(r) for r in results],
        "server_counters": server["counters"],
    }


def write_results(result: dict, out: Path,
                  page_lines: Sequence[str] = ()) -> tuple[Path, Path]:
    """OUT/latency.md (ending in ``page_lines``, the live-view section) and latency.json."""
    result, json_path = runner.save_json(out, "latency", result)
    stamp = result["date"]
    echo, overhead = result["echo_p50_us"], result["overhead_p50_us"]
    lines = [
        "# Round-trip latency (`burrforce bench latency`)",
        "",
        f"{stamp}; {result['machine']}. One run; echo, overhead and cutting samples "
        f"interleaved in chunks of {CHUNK}. Round trip: client stamps its packet (before "
        "encoding) → reply arrives (before decoding). Cutting: the workpiece at "
        f"{result['voxel_mm']:g} mm voxels, α = {ALPHA_DEG:g}°, {DEPTH_MM:g} mm deep, "
        f"{FEED_MM_S:g} mm/s, {RPM:g} rpm; its statistics are over the ticks that removed "
        f"bone. Placement: {result['placement']}.",
        "",
        "| run | pacing | samples | lost | p50 µs | p99 µs | p99.9 µs | max µs |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["runs"]:
        lines.append(f"| {r['mode']} | {r['pacing']} | {r['samples']} | {r['lost']} | "
                     f"{r['p50_us']:.0f} | {r['p99_us']:.0f} | {r['p999_us']:.0f} | "
                     f"{r['max_us']:.0f} |")
    lines += [
        "",
        f"Server-side model stage (carve + force, one numba call) in the cutting session: "
        f"p50 {result['server_tick_p50_us']:.0f} µs, p99 {result['server_tick_p99_us']:.0f} µs "
        "(last 8192 ticks).",
        "",
        "Waking ahead (`blocking`: the same cut on its own copy of the bone, in a second hot "
        "loop started with `--wake-ahead-us 0`, which sleeps in `epoll_wait` until each "
        "datagram as the echo does): round trip p50 "
        f"{result['blocking_p50_us']:.0f} µs and p99 {result['blocking_p99_us']:.0f} µs, "
        f"against {result['p50_us']:.0f} and {result['p99_us']:.0f} µs waking ahead; model "
        f"stage p50 {result['server_tick_blocking_p50_us']:.0f} µs. A loop that wakes ahead "
        "is running when the packet arrives, so it saves the wake-up the echo (and the "
        "blocking loop) pays"
        + (f": here the protocol alone took {result['overhead_p50_us']:.0f} µs against the "
           f"echo's {result['echo_p50_us']:.0f} µs." if result["overhead_p50_us"]
           < result["echo_p50_us"] else "."),
        "",
        "Scene features (`minimal`: no shaft, no vibration, no publishing to the control "
        "plane; the same cut on its own copy of the bone): round trip p50 "
        f"{result['minimal_p50_us']:.0f} µs against {result['p50_us']:.0f} µs with all on; "
        f"model stage p50 {result['server_tick_minimal_p50_us']:.0f} µs against "
        f"{result['server_tick_p50_us']:.0f} µs, p99 "
        f"{result['server_tick_minimal_p99_us']:.0f} against "
        f"{result['server_tick_p99_us']:.0f} µs.",
        "",
        f"A live view (`watched`: the same cut on its own copy of the bone while another "
        f"process samples its telemetry at {result['watch_hz']:g} Hz and encodes each "
        f"sample as the WebSocket does; {result['watched_samples']} samples): round "
        f"trip p50 {result['watched_p50_us']:.0f} µs against {result['p50_us']:.0f} µs "
        f"unwatched, p99 {result['watched_p99_us']:.0f} against {result['p99_us']:.0f} µs; "
        f"model stage p50 {result['server_tick_watched_p50_us']:.0f} against "
        f"{result['server_tick_p50_us']:.0f} µs.",
        "",
        "A CPU-bound task on the servers' CPU (`hogged` and `hogged blocking`: the same cut, "
        "each on its own copy of the bone in a hot loop of its own, one waking ahead and one "
        "not, while a busy loop that never blocks runs on their CPU, stopped during the other "
        "modes' chunks): round trip p50 "
        f"{result['hogged_p50_us']:.0f} µs and p99 {result['hogged_p99_us']:.0f} µs waking "
        f"ahead, against {result['hogged_blocking_p50_us']:.0f} and "
        f"{result['hogged_blocking_p99_us']:.0f} µs blocking. The waking loop's guard: "
        + ", ".join(f"{name.removeprefix('wake_')} {value:g}"
                    for name, value in result["hogged_wake_counters"].items())
        + " (`hotloop.wake`: `preempted`, a yield that came back later than the lead; "
        "`quiet`, a window skipped while backing off).",
        "",
        "Real-time (`realtime` and `hogged realtime`: the same cut, each on its own copy of "
        "the bone in a hot loop of its own started as `serve --realtime` does, SCHED_FIFO and "
        "blocking for each datagram"
        + ("" if all(result["realtime_granted"].values()) else
           "; SCHED_FIFO was NOT permitted here, so these loops ran at normal priority")
        + f"): round trip p50 {result['realtime_p50_us']:.0f} µs and p99 "
        f"{result['realtime_p99_us']:.0f} µs alone, {result['hogged_realtime_p50_us']:.0f} "
        f"and {result['hogged_realtime_p99_us']:.0f} µs beside the busy loop; against "
        f"{result['blocking_p50_us']:.0f} / {result['blocking_p99_us']:.0f} µs (`blocking`) "
        f"and {result['hogged_blocking_p50_us']:.0f} / "
        f"{result['hogged_blocking_p99_us']:.0f} µs (`hogged blocking`) at normal priority.",
        "",
        "Targets (1 kHz pacing):",
        f"- protocol overhead p50 ≤ 1.5 × echo p50: {overhead:.0f} µs against "
        f"1.5 × {echo:.0f} = {1.5 * echo:.0f} µs — "
        f"{'met' if overhead <= 1.5 * echo else 'NOT met'} (ratio {overhead / echo:.2f}).",
        f"- cutting p50 ≤ echo p50 + 100 µs: {result['p50_us']:.0f} µs against "
        f"{echo + 100:.0f} µs — {'met' if result['p50_us'] <= echo + 100 else 'NOT met'}.",
        f"- cutting p99 ≤ 500 µs (half the haptic period): {result['p99_us']:.0f} µs — "
        f"{'met' if result['p99_us'] <= 500 else 'NOT met'}.",
        f"- the same two for the loop that does not wake ahead: p50 "
        f"{result['blocking_p50_us']:.0f} µs against {echo + 100:.0f} µs — "
        f"{'met' if result['blocking_p50_us'] <= echo + 100 else 'NOT met'}; p99 "
        f"{result['blocking_p99_us']:.0f} µs — "
        f"{'met' if result['blocking_p99_us'] <= 500 else 'NOT met'}.",
        "",
        f"Server counters: {json.dumps(result['server_counters'])}",
    ]
    return runner.write_page(out, "latency", [*lines, *page_lines]), json_path


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    p = runner.add_bench(
        sub, "latency", main, help="UDP round trips: echo floor, protocol overhead, cutting",
        description="Round-trip latency through the real protocol and hot-loop process, "
                    "against a bare UDP echo, paced at 1 kHz and back-to-back. Writes "
                    "OUT/latency.md and latency.json.", json_help=runner.RESULTS_JSON)
    p.add_argument("--samples", type=int_in(500, 10_000_000, "sample count"), default=10_000,
                   help="round trips per run at 1 kHz. Default 10000 (10 s per run)")
    p.add_argument("--samples-b2b", type=int_in(500, 10_000_000, "sample count"),
                   default=20_000, help="round trips per back-to-back run. Default 20000")
    p.add_argument("--voxel-mm", type=float_in(0.05, 0.5, "voxel size", "mm"), default=0.1,
                   help="workpiece voxel size for the cutting run, mm. Default 0.1")
    p.add_argument("--no-page", action="store_true",
                   help="skip the live-view part (the browser view open and closed on a "
                        "session of the real stack). Only the project's own run measures "
                        "it, from a checkout: python -m benchmarks.latency (playwright and "
                        "/usr/bin/chromium)")
    return p


#: The live-view part's place in the results of a run that leaves it out.
PAGE_ELSEWHERE = "measured only by the project's own run (python -m benchmarks.latency)"


def page_section(page: dict) -> list[str]:
    """latency.md's live-view section when the part was skipped (``page["skipped"]``)."""
    return ["", f"Live view (`page closed` / `page open`): skipped — {page['skipped']}."]


def finish(args: argparse.Namespace, result: dict, out: Path, page_lines: Sequence[str]) -> int:
    """Write the results (``result["page"]`` holds the live-view part or why it is missing)
    and print them: ``--json`` prints the result with its runs last."""
    if result["page"].get("skipped"):
        runner.say(f"live view not measured: {result['page']['skipped']}")
    md, js = write_results(result, out, page_lines)
    return runner.report(args, md, js, rows={
        k: v for k, v in result.items() if k != "runs"} | {"runs": result["runs"]})


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    result = run(args.samples, args.samples_b2b, args.voxel_mm, progress=runner.say)
    result["page"] = {"skipped": "--no-page" if args.no_page else PAGE_ELSEWHERE}
    return finish(args, result, out, page_section(result["page"]))
