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
import json
import tempfile
import urllib.error
import urllib.request
from pathlib import Path

from ..argtypes import comma_separated, float_in, int_at_least
from . import runner
from .latency import ALPHA_DEG, DEPTH_MM, FEED_MM_S, RPM
from .serve_process import spawn_serve
from .soak import Rest
from .stations import (
    DRAIN_S,
    PHASES,
    RATE_SPREAD_PPM,
    Stream,
    drive,
    handshake,
    kernel_timestamps,
    open_stream,
    percentiles,
    station_clocks,
    tally,
)

DEFAULT_SESSIONS = (1, 2, 4, 8, 16)
VOXEL_MM = 0.1
TARGET = ("8 cutting sessions at 1 kHz: p99 < 1 ms and 0 lost; cost per session linear until "
          "the cores are busy")


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
        streams: list[Stream] = []
        try:
            c = serve.connection
            rest = Rest(c.http_url, c.token)
            view = json.loads(rest("GET", f"/v1/sessions/{c.session}"))
            streams.append(open_stream(c.host, c.udp_port, c.session, c.key_hex,
                                       view.get("worker")))
            for i in range(n - 1):
                progress(f"N = {n}: loading session {i + 2}/{n}'s workpiece")
                made = json.loads(rest("POST", "/v1/sessions", {
                    "bone": {"source": "phantom:workpiece", "voxel_mm": VOXEL_MM}}))
                if made.get("state") != "ready":
                    raise RuntimeError(f"session {made.get('id')} is {made.get('state')}: "
                                       f"{made.get('error')}")
                udp = made.get("udp") or {}  # a single loop: the connection's endpoint
                streams.append(open_stream(udp.get("host") or c.host,
                                           udp.get("port") or c.udp_port,
                                           made["id"], made["key"], made.get("worker")))
            health = _health(c.http_url)
            pids = _worker_pids(health)
            stamps = all([kernel_timestamps(s.sock) for s in streams])
            for s in streams:
                handshake(s)
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
    s50, s99 = percentiles(late_us, (50, 99))
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
    return runner.write_page(out, "sessions", lines), js


_counts = comma_separated(int, lambda n: 1 <= n <= 256, "session counts",
                         "session count must be in 1..256")


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
