"""``burrforce bench soak``: hours of a day at a simulator, squeezed: sessions streaming at 1 kHz
while the control plane churns, a junk flood hits the port and the hot loop is killed.

One ``burrforce serve`` in its own process. ``--sessions`` streaming clients, each in a process
of its own, cut back and forth through the workpiece at 1 kHz on an absolute schedule for the
whole run, and record every tick's round trip (NaN: no reply). This process drives REST churn
all along (create a session, PATCH it, export its mesh and volume, load a bone into it, delete
it; one operation every ``churn_s``) and samples the server's memory (the RSS of ``serve`` and
every process under it). The timeline, as fractions of ``--duration-s``:

    0.00–0.05 warm-up (not measured)   0.05–0.30 quiet      0.30–0.40 flood (100 000/s junk)
    0.40–0.60 after the flood          0.60      the hot loop killed (SIGKILL)
    0.60–1.00 after the kill (less the recovery)

Reported: replies lost and round-trip p50/p99 per phase, each client's recovery (from the
kill to its first reply after it), the replies lost inside and outside recovery, REST
operations and their errors, and RSS at the start of the measured run and at its end.
Targets (issue 19): nothing lost outside recovery; recovery ≤ 2 s; RSS drift ≤ 2 %; flood
p99 ≤ 2 × quiet p99.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
import signal
import socket
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np

from . import runner
from .flood import flood
from .serve_process import spawn_serve

PHASES = (("quiet", 0.05, 0.30), ("flood", 0.30, 0.40), ("after_flood", 0.40, 0.60),
          ("after_kill", 0.60, 1.00))
KILL_AT = 0.60
FLOOD_RATE_HZ = 100_000.0
#: The cut: back and forth along x at this speed, this deep in the workpiece, mm, mm/s.
CUT_X_MM = (3.0, 23.0)
CUT_SPEED_MM_S = 2.0
CUT_DEPTH_MM = 0.4


def _cut_position(i: int, lane: int) -> tuple[float, float, float]:
    """Tick ``i``'s burr centre for client ``lane`` (its own y, so lanes never meet)."""
    x0, x1 = CUT_X_MM
    span = x1 - x0
    d = (i * 1e-3 * CUT_SPEED_MM_S) % (2 * span)
    x = x0 + (d if d < span else 2 * span - d)
    return (x, -6.0 + 3.0 * lane, -CUT_DEPTH_MM)


def stream_client(host: str, port: int, session: int, key: str | None, lane: int,
                  start_at: float, duration_s: float, out: str) -> None:
    """Stream ticks from ``start_at`` for ``duration_s`` at 1 kHz; save every tick's round
    trip, µs (NaN: no reply), to ``out`` (.npy).

    Each pose is stamped when it is sent (as an engine stamps its sample), so the round trip
    is the server's and the network's, not this process's lateness; the schedule is kept
    by sleeping, not spinning (a spinning client would take the server's core), and the
    socket's buffer holds seconds of replies, so a client that falls behind loses none."""
    from ...client.udp import BurrClient, ServerGone
    from ...proto.messages import Notice

    n = int(duration_s * 1000)
    rtt = np.full(n, np.nan)
    tick_of: dict[int, int] = {}
    with BurrClient(host, port, session, key, timeout_s=0.0) as client:
        client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)

        def drain() -> None:
            while True:
                try:
                    m = client.receive(0.0)
                except ServerGone:
                    continue
                if m is None:
                    return
                if not isinstance(m, Notice):
                    i = tick_of.pop(m.reply.seq, None)
                    if i is not None and m.reply.error == 0:
                        rtt[i] = m.rtt_us
        for i in range(n):
            left = start_at + i * 1e-3 - time.monotonic()
            if left > 0:
                time.sleep(left)
            try:
                seq = client.send(_cut_position(i, lane), rpm=60000.0)
                tick_of[seq] = i
            except ServerGone:
                pass
            drain()
            if len(tick_of) > 5000:  # replies that never came: forget the oldest
                for seq in list(tick_of)[:1000]:
                    del tick_of[seq]
        end = time.monotonic() + 0.3
        while time.monotonic() < end:
            drain()
            time.sleep(0.005)
    np.save(out, rtt)


def _rss_kb(pid: int) -> int:
    """RSS of ``pid`` and every process under it, kB."""
    total = 0
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            for line in Path(f"/proc/{p}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1])
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, ValueError):
            pass
    return total


class Rest:
    def __init__(self, url: str, token: str) -> None:
        self.url, self.token = url, token

    def __call__(self, method: str, path: str, body: dict | None = None) -> bytes:
        req = urllib.request.Request(
            self.url + path, method=method,
            data=None if body is None else json.dumps(body).encode(),
            headers={"Authorization": f"Bearer {self.token}",
                     "Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=60) as r:
            return r.read()


def churn(rest: Rest, stop: threading.Event, every_s: float, stats: dict) -> None:
    """Create, PATCH, export, load and delete sessions until ``stop``."""
    ops = (
        lambda s: rest("PATCH", f"/v1/sessions/{s}/parameters", {"us_n_mm2": 900.0}),
        lambda s: rest("GET", f"/v1/sessions/{s}/export/mesh"),
        lambda s: rest("GET", f"/v1/sessions/{s}/export/volume?format=npy"),
        lambda s: rest("PUT", f"/v1/sessions/{s}/bone",
                       {"source": "phantom:workpiece", "voxel_mm": 0.5}),
    )
    while not stop.is_set():
        try:
            made = json.loads(rest("POST", "/v1/sessions", {
                "bone": {"source": "phantom:workpiece", "voxel_mm": 0.5}}))
            stats["ops"] += 1
            for op in ops:
                if stop.wait(every_s):
                    break
                op(made["id"])
                stats["ops"] += 1
            rest("DELETE", f"/v1/sessions/{made['id']}")
            stats["ops"] += 1
        except (urllib.error.URLError, OSError, ValueError) as exc:
            stats["errors"] += 1
            body = exc.read().decode(errors="replace") if isinstance(
                exc, urllib.error.HTTPError) else ""
            stats["last_error"] = f"{exc} {body}"[:300]
            stop.wait(every_s)
        stop.wait(every_s)


def run(duration_s: float, sessions: int, churn_s: float, voxel_mm: float = 0.2,
        progress=print) -> dict:
    with tempfile.TemporaryDirectory(prefix="burrforce-bench-soak-") as tmp:
        serve = spawn_serve(Path(tmp), "--bone", "phantom:workpiece", "--voxel-mm",
                            str(voxel_mm))
        try:
            result = _run(serve, Path(tmp), duration_s, sessions, churn_s, voxel_mm,
                          progress)
            return {**result, "voxel_mm": voxel_mm, "churn_s": churn_s}
        finally:
            serve.stop()


def _run(serve, tmp: Path, duration_s: float, sessions: int, churn_s: float,
         voxel_mm: float, progress) -> dict:
    c = serve.connection
    rest = Rest(c.http_url, c.token)
    ids = [(c.session, c.key_hex)]
    for _ in range(sessions - 1):
        made = json.loads(rest("POST", "/v1/sessions", {
            "bone": {"source": "phantom:workpiece", "voxel_mm": voxel_mm}}))
        ids.append((made["id"], made["key"]))
    ctx = multiprocessing.get_context("spawn")
    start = time.monotonic() + 3.0
    clients = []
    for lane, (sid, key) in enumerate(ids):
        out = str(tmp / f"rtt-{sid}.npy")
        p = ctx.Process(target=stream_client, args=(c.host, c.udp_port, sid, key, lane,
                                                   start, duration_s, out))
        p.start()
        clients.append((sid, p, out))
    sent = ctx.Value("q", 0)
    flooder = ctx.Process(target=flood, args=(c.host, c.udp_port, FLOOD_RATE_HZ,
                                              duration_s * (PHASES[1][2] - PHASES[1][1]),
                                              "junk", 1, c.session,
                                              start + duration_s * PHASES[1][1], sent))
    flooder.start()
    stop = threading.Event()
    churn_stats = {"ops": 0, "errors": 0, "last_error": None}
    churner = threading.Thread(target=churn, args=(rest, stop, churn_s, churn_stats),
                               daemon=True)
    while time.monotonic() < start:
        time.sleep(0.01)
    churner.start()
    rss = []
    killed_at = None
    while True:
        t = time.monotonic() - start
        if t >= duration_s:
            break
        rss.append((t, _rss_kb(serve.proc.pid)))
        if killed_at is None and t >= KILL_AT * duration_s:
            health = json.loads(urllib.request.urlopen(c.http_url + "/v1/health",
                                                       timeout=10).read())
            os.kill(health["supervisor"]["pid"], signal.SIGKILL)
            killed_at = time.monotonic() - start
            progress(f"{t:6.1f} s: killed the hot loop (pid {health['supervisor']['pid']})")
        time.sleep(min(1.0, max(0.05, KILL_AT * duration_s - t)) if killed_at is None
                   else 1.0)
        if int(t) % 60 == 0 and t > 1:
            progress(f"{t:6.0f} s of {duration_s:.0f}: RSS {rss[-1][1] / 1024:.0f} MB, "
                     f"REST ops {churn_stats['ops']}")
    stop.set()
    churner.join(60)
    for _, p, _ in clients:
        p.join(120)
    flooder.join(30)
    health = json.loads(urllib.request.urlopen(c.http_url + "/v1/health", timeout=10).read())
    return summarize(clients, duration_s, killed_at, rss, churn_stats, int(sent.value),
                     health)


def summarize(clients, duration_s: float, killed_at: float, rss, churn_stats: dict,
              flood_sent: int, health: dict) -> dict:
    per_client = []
    all_phases: dict[str, list[np.ndarray]] = {name: [] for name, _, _ in PHASES}
    lost_outside = lost_inside = 0
    for sid, _, out in clients:
        rtt = np.load(out)
        kill_i = int(killed_at * 1000)
        after = np.flatnonzero(~np.isnan(rtt[kill_i:]))
        recovered_i = kill_i + int(after[0]) if len(after) else len(rtt)
        recovery_s = (recovered_i - kill_i) * 1e-3
        phases = {}
        for name, a, b in PHASES:
            lo, hi = int(a * duration_s * 1000), int(b * duration_s * 1000)
            if name == "after_kill":
                lo = max(lo, recovered_i)
            seg = rtt[lo:hi]
            ok = seg[~np.isnan(seg)]
            all_phases[name].append(ok)
            phases[name] = {"ticks": len(seg), "lost": int(np.isnan(seg).sum()),
                            "p50_us": float(np.median(ok)) if len(ok) else None,
                            "p99_us": float(np.percentile(ok, 99)) if len(ok) else None}
            lost_outside += phases[name]["lost"]
        lost_inside += int(np.isnan(rtt[kill_i:recovered_i]).sum())
        per_client.append({"session": sid, "recovery_s": recovery_s, "phases": phases})
    merged = {}
    for name, parts in all_phases.items():
        ok = np.concatenate(parts) if parts else np.zeros(0)
        merged[name] = {"p50_us": float(np.median(ok)) if len(ok) else None,
                        "p99_us": float(np.percentile(ok, 99)) if len(ok) else None,
                        "replies": len(ok)}
    measured = [kb for t, kb in rss if t >= PHASES[0][1] * duration_s]
    rss_start = float(np.median(measured[:10])) if measured else math.nan
    rss_end = float(np.median(measured[-10:])) if measured else math.nan
    quiet99, flood99 = merged["quiet"]["p99_us"], merged["flood"]["p99_us"]
    return {
        "duration_s": duration_s, "sessions": len(clients), "killed_at_s": killed_at,
        "flood_sent": flood_sent, "clients": per_client, "phases": merged,
        "lost_outside_recovery": lost_outside, "lost_in_recovery": lost_inside,
        "recovery_s_max": max(c["recovery_s"] for c in per_client),
        "rss_kb_start": rss_start, "rss_kb_end": rss_end,
        "rss_drift": (rss_end - rss_start) / rss_start if rss_start else None,
        "flood_p99_ratio": flood99 / quiet99 if quiet99 and flood99 else None,
        "rest": churn_stats, "server_health": health,
        "server_restart": health.get("supervisor", {}).get("last_restart"),
    }


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, js = runner.save_json(out, "soak", result, utc=True)
    stamp = result["date"]
    r = result

    def ok(flag: bool) -> str:
        return "met" if flag else "**missed**"

    restart = r["server_restart"] or {}
    lines = [
        f"# bench soak: {r['duration_s'] / 60:g} min, {r['sessions']} sessions at 1 kHz, "
        "REST churn, a flood and a killed hot loop", "",
        f"Streaming sessions cut the workpiece at {r['voxel_mm']:g} mm voxels; one REST "
        f"operation every {r['churn_s']:g} s (create, PATCH, export mesh, export volume, load "
        "a bone, delete); 100 000 junk datagrams/s during the flood phase.", "",
        f"{stamp}; {r['machine']}. Generated by `burrforce bench soak`; see "
        "server/bench/soak.py for the method.", "",
        "| phase | replies | RTT p50 µs | RTT p99 µs |", "|---|---|---|---|",
    ]
    for name, _, _ in PHASES:
        p = r["phases"][name]
        lines.append(f"| {name} | {p['replies']} | {p['p50_us'] or 0:.0f} | "
                     f"{p['p99_us'] or 0:.0f} |")
    drift = r["rss_drift"]
    ratio = r["flood_p99_ratio"]
    lines += [
        "",
        "| target | measured | |", "|---|---|---|",
        f"| 0 replies lost outside recovery | {r['lost_outside_recovery']} | "
        f"{ok(r['lost_outside_recovery'] == 0)} |",
        f"| recovery ≤ 2 s (kill → each client's first reply) | {r['recovery_s_max']:.3f} s "
        f"| {ok(r['recovery_s_max'] <= 2.0)} |",
        f"| RSS drift ≤ 2 % | {100 * drift:+.2f} % ({r['rss_kb_start'] / 1024:.0f} → "
        f"{r['rss_kb_end'] / 1024:.0f} MB) | {ok(abs(drift) <= 0.02)} |",
        f"| flood p99 ≤ 2 × quiet p99 | {ratio:.2f} × | {ok(ratio <= 2.0)} |",
        "",
        f"Replies lost inside the recovery: {r['lost_in_recovery']}. The server's own account "
        f"of the restart: {restart.get('reason')}, sessions back in "
        f"{restart.get('recovery_s')} s. Flood: {r['flood_sent']} datagrams. REST: "
        f"{r['rest']['ops']} operations, {r['rest']['errors']} errors"
        + (f" (last: {r['rest']['last_error']})" if r["rest"]["errors"] else "") + ".",
    ]
    return runner.write_page(out, "soak", lines), js


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "soak", main,
        help="sessions at 1 kHz with REST churn, a junk flood and a hot-loop kill",
        description="Run `burrforce serve` for a while under everything at once: streaming "
                    "sessions, REST churn, a 100 000/s junk flood, a SIGKILL of the hot loop. "
                    "Reports lost replies, round trips per phase, recovery time and memory "
                    "drift. Writes soak.md and soak.json.")
    p.add_argument("--duration-s", type=float, default=600.0,
                   help="seconds of streaming. Default 600")
    p.add_argument("--sessions", type=int, default=2, help="streaming sessions. Default 2")
    p.add_argument("--voxel-mm", type=float, default=0.2,
                   help="the streaming sessions' workpiece voxel size, mm. Default 0.2 (at "
                        "0.1 mm two sessions cutting at 1 kHz fill the one hot-loop thread of "
                        "a 2-core machine)")
    p.add_argument("--churn-s", type=float, default=0.5,
                   help="seconds between REST operations. Default 0.5")


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    return runner.report(args, *write_results(
        run(args.duration_s, args.sessions, args.churn_s, args.voxel_mm, runner.say), out))
