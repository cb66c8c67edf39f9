"""``burrforce bench flood``: does a keyed session keep its round trip while junk floods the port?

One run per (kind, senders): ``burrforce serve`` in its own process; this process streams the
default (keyed) session at 1 kHz through a cut for ``quiet + flood + quiet`` seconds; a third
process sends datagrams to the same UDP port at ``rate`` per second during the middle phase,
from ``senders`` sockets in turn. Kinds:

- ``junk``: random bytes (decoding fails);
- ``foreign``: well-formed, tagged POSEs for the streaming session with another key (each
  costs the server a decode and an HMAC: the most expensive thing a stranger can send);
- ``unknown``: well-formed POSEs for a session that does not exist.

Reported per phase: replies lost, round trip p50/p99/max, and the flood's own count; the
server's counters after the run (what it read, what it refused).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import socket
import tempfile
import time
from pathlib import Path

import numpy as np

from . import runner
from .serve_process import spawn_serve

PHASES = ("quiet", "flood", "after")
KINDS = ("junk", "foreign", "unknown")


def _payloads(kind: str, session: int, n: int = 64) -> list[bytes]:
    from ...proto.codec import encode_pose
    from ...proto.messages import Pose
    from ...proto.tag import Tagger

    if kind == "junk":
        return [os.urandom(100) for _ in range(n)]
    sid = session if kind == "foreign" else 0xFFFF_FF00
    tagger = Tagger(os.urandom(32)) if kind == "foreign" else None
    fields = Pose._fields
    out = []
    for i in range(n):
        values = {"session": sid, "seq": 1000 + i, "t_client_us": 10**9 + i,
                  "position": (1.0, 2.0, 3.0), "orientation": (0.0, 0.0, 0.0, 1.0),
                  "rpm": 60000.0, "spindle_on": True}
        if "stream" in fields:  # protocol v2: an open stream number, not a hello
            values["stream"] = 12345
        out.append(encode_pose(Pose(**values), tagger))
    return out


def flood(host: str, port: int, rate_hz: float, seconds: float, kind: str, senders: int,
          session: int, start_at: float, sent: multiprocessing.Value) -> None:
    """Send ``rate_hz`` datagrams a second for ``seconds`` from ``senders`` sockets, on an
    absolute 1 ms schedule starting at ``start_at`` (time.monotonic)."""
    payloads = _payloads(kind, session)
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    socks = [socket.socket(family, socket.SOCK_DGRAM) for _ in range(senders)]
    for s in socks:
        s.setblocking(False)
    per_ms = rate_hz / 1000.0
    due = 0.0
    n = 0
    while time.monotonic() < start_at:
        time.sleep(0.001)
    end = start_at + seconds
    tick = 0
    while True:
        now = time.monotonic()
        if now >= end:
            break
        target = (now - start_at) * 1000.0 * per_ms
        while due < target:
            s = socks[n % senders]
            try:
                s.sendto(payloads[n % len(payloads)], (host, port))
            except (BlockingIOError, OSError):
                pass
            n += 1
            due += 1.0
        tick += 1
        next_t = start_at + tick * 0.001
        delay = next_t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
    sent.value = n
    for s in socks:
        s.close()


def _metrics(url: str, token: str) -> dict[str, float]:
    import urllib.request

    req = urllib.request.Request(url + "/metrics", headers={"Authorization": f"Bearer {token}"})
    text = urllib.request.urlopen(req, timeout=10).read().decode()
    out = {}
    for line in text.splitlines():
        if line.startswith("burrforce_packets_total{"):
            name = line.split('outcome="', 1)[1].split('"', 1)[0]
            out[name] = float(line.rsplit(" ", 1)[1])
    return out


def one_run(tmp: Path, kind: str, senders: int, rate_hz: float, phase_s: float,
            progress=print) -> dict:
    """One serve, one stream, one flood in its middle phase."""
    from ...client.trajectory import line, stream
    from ...client.udp import BurrClient

    serve = spawn_serve(tmp / f"{kind}-{senders}", "--bone", "phantom:workpiece",
                        "--voxel-mm", "0.1")
    try:
        c = serve.connection
        total_s = 3 * phase_s
        ctx = multiprocessing.get_context("spawn")
        sent = ctx.Value("q", 0)
        with BurrClient(c.host, c.udp_port, c.session, c.key_hex, timeout_s=0.2) as client:
            # Hello and warm the path before the clock starts (protocol v2 opens a stream).
            for _ in range(50):
                try:
                    client.exchange((2.0, 0.0, 10.0))
                    break
                except (TimeoutError, OSError):
                    time.sleep(0.02)
            start = time.monotonic() + 1.0
            flooder = ctx.Process(target=flood, args=(c.host, c.udp_port, rate_hz, phase_s,
                                                      kind, senders, c.session,
                                                      start + phase_s, sent))
            flooder.start()
            while time.monotonic() < start:
                time.sleep(0.001)
            # A slow, shallow cut along the workpiece for the whole run.
            path = line((2.0, 0.0, -0.3), (2.0 + total_s * 1.0, 0.0, -0.3), 1.0,
                        rpm=60000.0)
            result = stream(client, path, 1000.0, linger_s=0.2)
            flooder.join(30)
        counters = _metrics(c.http_url, c.token)
    finally:
        serve.stop()
    n = len(result.results)
    per_phase = n / 3
    phases = {}
    for k, name in enumerate(PHASES):
        chunk = result.results[int(k * per_phase):int((k + 1) * per_phase)]
        rtt = np.array([r.rtt_us for r in chunk if r is not None])
        phases[name] = {
            "ticks": len(chunk), "lost": sum(r is None for r in chunk),
            "rtt_p50_us": float(np.median(rtt)) if len(rtt) else None,
            "rtt_p99_us": float(np.percentile(rtt, 99)) if len(rtt) else None,
            "rtt_max_us": float(rtt.max()) if len(rtt) else None,
        }
    out = {"kind": kind, "senders": senders, "rate_hz": rate_hz, "phase_s": phase_s,
           "flood_sent": int(sent.value), "late_sends": result.late_sends,
           "phases": phases, "server_counters": counters}
    q, f = phases["quiet"], phases["flood"]
    progress(f"{kind:8s} x{senders:<3d} sent {out['flood_sent']:7d}: quiet p99 "
             f"{q['rtt_p99_us'] or 0:7.0f} µs lost {q['lost']}, flood p99 "
             f"{f['rtt_p99_us'] or 0:7.0f} µs lost {f['lost']}")
    return out


def run(progress=print, rate_hz: float = 100_000.0, phase_s: float = 5.0,
        cases: tuple[tuple[str, int], ...] = (("junk", 1), ("junk", 16), ("foreign", 1),
                                              ("unknown", 16))) -> dict:
    with tempfile.TemporaryDirectory(prefix="burrforce-bench-flood-") as tmp:
        runs = [one_run(Path(tmp), kind, senders, rate_hz, phase_s, progress)
                for kind, senders in cases]
    return {"rate_hz": rate_hz, "phase_s": phase_s, "runs": runs}


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, js = runner.save_json(out, "flood", result, utc=True)
    stamp = result["date"]
    lines = [
        "# bench flood: a keyed session at 1 kHz while the port is flooded", "",
        f"{stamp}; {result['machine']}. Generated by `burrforce bench flood`; "
        "see server/bench/flood.py for the method.", "",
        f"Flood: {result['rate_hz']:.0f} datagrams/s during the middle "
        f"{result['phase_s']:g} s of {3 * result['phase_s']:g} s of streaming.", "",
        "| kind | senders | flood sent | phase | lost | RTT p50 µs | RTT p99 µs | RTT max µs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        for name in PHASES:
            p = r["phases"][name]
            lines.append(f"| {r['kind']} | {r['senders']} | {r['flood_sent']} | {name} | "
                         f"{p['lost']}/{p['ticks']} | {p['rtt_p50_us'] or 0:.0f} | "
                         f"{p['rtt_p99_us'] or 0:.0f} | {p['rtt_max_us'] or 0:.0f} |")
    lines += ["", "Server counters after each run (datagrams by outcome):", ""]
    for r in result["runs"]:
        c = {k: int(v) for k, v in r["server_counters"].items() if v}
        lines.append(f"- {r['kind']} x{r['senders']}: {c}")
    return runner.write_page(out, "flood", lines), js


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "flood", main, help="a keyed session's round trip while junk floods the UDP port",
        description="Stream a keyed session at 1 kHz through `burrforce serve` while another "
                    "process floods its UDP port (random bytes, forged POSEs, unknown "
                    "sessions; one or many senders); report lost replies and round trips "
                    "per phase. Writes flood.md and flood.json.")
    p.add_argument("--rate", type=float, default=100_000.0,
                   help="flood datagrams per second. Default 100000")
    p.add_argument("--phase-s", type=float, default=5.0,
                   help="seconds per phase (quiet, flood, after). Default 5")


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    return runner.report(args, *write_results(run(runner.say, args.rate, args.phase_s), out))
