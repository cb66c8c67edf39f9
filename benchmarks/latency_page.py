"""``bench latency``'s live-view part: round trips of one cutting session with the browser view
(``/ui/``) open on it and closed, in one run.

The view needs the REST control plane, so this part runs the real stack (``ServerStack``: the
hot loop, the control plane, uvicorn) with one cutting session on the workpiece, in a process
of its own as ``burrforce serve`` runs it (in the client's process, the page's WebSockets would
take the client's interpreter lock: a cost no engine pays); ``bench latency``'s client streams
its cut to it at 1 kHz. Chunks of ``page closed`` (headless chromium idle on about:blank: the page's
WebSockets closed) and ``page open`` (the page loaded on the session, and live, before the
chunk starts: its load is not measured) alternate on the same session and groove, which goes
on through the chunks. The hot loop and the client are pinned as ``bench latency`` pins them;
chromium and the stack's own process (which serves the page) are not, as on a user's machine.

``python -m benchmarks.latency_page VOXEL_MM DATA_DIR`` is the stack's process: it
prints the session's addresses as one JSON line and serves until its stdin closes.
"""

from __future__ import annotations

import contextlib
import gc
import json
import os
import secrets
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from burrforce.server.bench.latency import (
    CHUNK,
    GrooveCut,
    StreamClient,
    page_section,
    pin_cpus,
    run_stats,
)
from burrforce.server.bench.procstat import children, cpu_s
from support.chromium import WEBGL_ARGS, launch, missing

from . import child_env

MODES = ("page closed", "page open")
SESSION_ID = 1
TOKEN_ENV = "BURRFORCE_BENCH_PAGE_TOKEN"
#: The page's first load meshes the whole workpiece (seconds in SwiftShader at 0.1 mm).
LIVE_TIMEOUT_MS = 180_000
#: After leaving the page: the server's WebSocket handlers see the close and end.
SETTLE_S = 0.5
VIEWPORT = {"width": 1400, "height": 850}
#: The browser's niceness (``_renice_browser``).
BROWSER_NICE = 19
LIVE = (f"() => window.burrforceView && burrforceView.state.selected === {SESSION_ID} "
        "&& burrforceView.state.copy && burrforceView.state.copy.have !== null "
        "&& burrforceView.plots.samples > 0 && burrforceView.scene.frames > 0")
COUNTERS = ("() => ({frames: burrforceView.scene.frames, samples: burrforceView.plots.samples, "
            "mesh: burrforceView.state.meshUpdates, version: burrforceView.state.copy.have})")
STATE = ("() => window.burrforceView ? {selected: burrforceView.state.selected, "
         "have: burrforceView.state.copy && burrforceView.state.copy.have, "
         "samples: burrforceView.plots.samples, frames: burrforceView.scene.frames, "
         "mesh: document.getElementById('mesh-status').textContent} : document.title")


def _serve(voxel_mm: float, data_dir: Path) -> int:
    from burrforce.server.api.config import ServeConfig
    from burrforce.server.api.models import Parameters
    from burrforce.server.api.stack import ServerStack

    config = ServeConfig(http_port=0, udp_port=0, workers=1, data_dir=data_dir)
    with ServerStack(config, os.environ.pop(TOKEN_ENV), journal=False) as stack:
        source = stack.plane.resolve("phantom:workpiece", None, voxel_mm)  # type: ignore[union-attr]
        session = stack.add_session(source, Parameters(), session_id=SESSION_ID)
        print(json.dumps({"url": stack.url, "udp": list(stack.udp_address),
                          "hot_pid": stack.hot.pid, "key_hex": session.key_hex}),  # type: ignore[union-attr]
              flush=True)
        sys.stdin.read()
    return 0


def _subtree(root: int, tree: dict[int, list[int]]) -> list[int]:
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += tree.get(pid, [])
    return out


def _exe_name(pid: int) -> str:
    try:
        return os.path.basename(os.readlink(f"/proc/{pid}/exe"))
    except OSError:
        return ""


def _cpu_s(pids: list[int]) -> dict[int, float]:
    """utime + stime of each live pid, s."""
    return {pid: t for pid in pids if (t := cpu_s(pid)) is not None}


GROUPS = ("browser", "driver", "stack", "hot_loop")


class _Processes:
    """CPU time of this process's descendants, by group: chromium's tree (``browser``),
    playwright's driver, the stack's process (control plane, uvicorn; ``stack``) and its hot
    loop."""

    def __init__(self, stack_pid: int, hot_pid: int) -> None:
        self.stack_pid = stack_pid
        self.hot_pid = hot_pid

    def snapshot(self) -> dict[str, dict[int, float]]:
        tree = children()
        groups: dict[str, list[int]] = {g: [] for g in GROUPS}
        for child in tree.get(os.getpid(), []):
            for pid in _subtree(child, tree):
                if pid == self.hot_pid:
                    groups["hot_loop"].append(pid)
                elif child == self.stack_pid:
                    groups["stack"].append(pid)
                else:
                    groups["driver" if _exe_name(pid) == "node" else "browser"].append(pid)
        return {g: _cpu_s(pids) for g, pids in groups.items()}


def _delta(after: dict[int, float], before: dict[int, float]) -> float:
    # A process born during the chunk counts whole; one that ended in it is lost (none should).
    return sum(t - before.get(pid, 0.0) for pid, t in after.items())


def run(samples: int, voxel_mm: float, rate_hz: float = 1000.0, chunk: int = CHUNK,
        cpus: set[int] | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """The live-view part: ``samples`` round trips per mode in chunks of ``chunk``, alternating
    closed and open. ``cpus``: the CPUs the stack and the browser may use (``bench latency``
    has pinned this process by then; default: this process's affinity). Returns
    ``{"skipped": reason}`` where playwright or chromium is missing."""
    reason = missing()
    if reason is not None:
        return {"skipped": reason}
    from playwright.sync_api import sync_playwright

    say = progress or (lambda text: None)
    affinity = os.sched_getaffinity(0)
    # Children inherit the affinity: the stack and the browser start unpinned.
    os.sched_setaffinity(0, cpus or affinity)
    token = secrets.token_hex(16)
    data = tempfile.TemporaryDirectory(prefix="burrforce-bench-page-")
    say("live view: starting the stack (workpiece, one cutting session) and chromium")
    stack = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.latency_page", str(voxel_mm), data.name],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
        env=child_env({TOKEN_ENV: token}))
    try:
        line = stack.stdout.readline()  # type: ignore[union-attr]
        if not line:
            raise RuntimeError("the stack's process exited before its session was ready")
        info = json.loads(line)
        with sync_playwright() as pw:
            browser = launch(pw, WEBGL_ARGS)
            _renice_browser(stack.pid)
            try:
                return _measure(browser, info, token, samples, voxel_mm, rate_hz, chunk,
                                _Processes(stack.pid, info["hot_pid"]),
                                lambda: _renice_browser(stack.pid), say)
            finally:
                browser.close()
    finally:
        stack.stdin.close()  # type: ignore[union-attr]
        try:
            stack.wait(30.0)
        except subprocess.TimeoutExpired:
            stack.kill()
            stack.wait()
        data.cleanup()
        os.sched_setaffinity(0, affinity)
        gc.unfreeze()


def _browser_threads(stack_pid: int) -> list[int]:
    """Every thread of chromium's processes (not the stack's, not playwright's node)."""
    tree = children()
    tids = []
    for child in tree.get(os.getpid(), []):
        if child == stack_pid:
            continue
        for pid in _subtree(child, tree):
            if _exe_name(pid) != "node":
                with contextlib.suppress(OSError):
                    tids += [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    return tids


def _renice_browser(stack_pid: int) -> tuple[int, int]:
    """Every chromium thread to ``BROWSER_NICE`` (niceness is a thread's on Linux; chromium
    raises some of its own threads, so this is done again before each open chunk): a page
    watching the haptic machine should take only CPU the server and the engine leave, as
    ``nice -n 19`` asks for a user's browser. Returns (threads at BROWSER_NICE, threads).
    (SCHED_IDLE for the processes as well was tried: no better.)"""
    tids = _browser_threads(stack_pid)
    at = 0
    for tid in tids:
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, tid, BROWSER_NICE)
        with contextlib.suppress(OSError):
            at += os.getpriority(os.PRIO_PROCESS, tid) == BROWSER_NICE
    return at, len(tids)


def _measure(browser, info: dict, token: str, samples: int, voxel_mm: float, rate_hz: float,
             chunk: int, processes: _Processes, renice: Callable[[], tuple[int, int]],
             say: Callable[[str], None]) -> dict:
    context = browser.new_context(service_workers="block", viewport=VIEWPORT)
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(f"page: {e}"))
    page.on("console", lambda m: errors.append(f"console: {m.text}") if m.type == "error"
            else None)
    page.goto("about:blank")
    placement = pin_cpus(info["hot_pid"])
    url = f"{info['url']}/ui/#token={token}&session={SESSION_ID}"
    client = StreamClient(tuple(info["udp"]), SESSION_ID, bytes.fromhex(info["key_hex"]),
                          GrooveCut())
    period = 1.0 / rate_hz
    kept = {m: {"rtt": [], "cutting": [], "lost": 0, "wall_s": 0.0} | dict.fromkeys(GROUPS, 0.0)
            for m in MODES}
    frames = telemetry = mesh = 0
    niced = (0, 0)
    load_s: list[float] = []
    gl = ""
    done = 0
    while done < samples:
        n = min(chunk, samples - done)
        for mode in MODES:
            if mode == "page open":
                t = time.monotonic()
                page.goto(url, wait_until="load")
                try:
                    page.wait_for_function(LIVE, timeout=LIVE_TIMEOUT_MS)
                except Exception as exc:
                    raise RuntimeError(f"the page did not get live: {page.evaluate(STATE)}; "
                                       f"its errors: {errors}") from exc
                load_s.append(time.monotonic() - t)
                gl = gl or page.evaluate("() => burrforceView.scene.glRenderer")
                niced = renice()
                before = page.evaluate(COUNTERS)
            # Our collector's pauses must fall in neither mode; frozen objects are not walked.
            gc.collect()
            gc.freeze()
            client.rtt_us, client.cutting, client.lost = [], [], 0
            cpu_before = processes.snapshot()
            t0 = time.monotonic()
            client.chunk(n, period)
            wall = time.monotonic() - t0
            cpu_after = processes.snapshot()
            k = kept[mode]
            k["rtt"] += client.rtt_us
            k["cutting"] += client.cutting
            k["lost"] += client.lost
            k["wall_s"] += wall
            for g in GROUPS:
                k[g] += _delta(cpu_after[g], cpu_before[g])
            if mode == "page open":
                after = page.evaluate(COUNTERS)
                frames += after["frames"] - before["frames"]
                telemetry += after["samples"] - before["samples"]
                mesh += after["mesh"] - before["mesh"]
                page.goto("about:blank")
                time.sleep(SETTLE_S)
        done += n
        say(f"live view: {done}/{samples}")
    context.close()
    runs = []
    for mode in MODES:
        k = kept[mode]
        rtt = np.array(k["rtt"])
        mask = np.array(k["cutting"], dtype=bool)
        row = asdict(run_stats(mode, f"{rate_hz:g} Hz" if rate_hz != 1000.0 else "1 kHz",
                            rtt[mask], k["lost"], float(mask.mean()) if len(mask) else 0.0))
        row["wall_s"] = k["wall_s"]
        row |= {f"{g}_cpu_pct": 100.0 * k[g] / k["wall_s"] for g in GROUPS}
        if mode == "page open":
            row |= {"frames": frames, "telemetry_samples": telemetry, "mesh_updates": mesh}
        runs.append(row)
    return {
        "skipped": None,
        "runs": runs,
        "voxel_mm": voxel_mm,
        "chunk": chunk,
        "placement": f"{placement}; the stack's process and chromium not pinned",
        "gl_renderer": gl,
        "browser_version": browser.version,
        "page_live_s_median": float(np.median(load_s)) if load_s else None,
        "page_errors": errors[:10],
        # Before the last open chunk: chromium's threads at BROWSER_NICE, of all of them.
        "browser_threads_niced": list(niced),
    }


def markdown(page: dict) -> list[str]:
    """``latency.md``'s live-view section: a paragraph and a table (or why it was skipped)."""
    if page.get("skipped"):
        return page_section(page)
    closed, opened = page["runs"]
    wall = opened["wall_s"]
    lines = [
        "",
        "Live view (`page open`: the browser view `/ui/` open on the session in headless "
        f"chromium {page['browser_version']}, WebGL in software ({page['gl_renderer']}); "
        "`page closed`: the same browser idle on about:blank, the page's WebSockets closed). "
        "The real stack (`ServerStack`: hot loop, control plane, uvicorn) in its own process, "
        f"one cutting session on the workpiece at {page['voxel_mm']:g} mm voxels, the same cut "
        "as `cutting`, one groove going on through the chunks; closed and open chunks of "
        f"{page['chunk']} interleaved; before each open chunk the page was loaded and live "
        f"(mesh copy complete, telemetry arriving; median {page['page_live_s_median']:.1f} s, "
        f"not measured). Placement: {page['placement']}; every chromium thread set to nice "
        f"{BROWSER_NICE} (the lowest priority) before each open chunk "
        f"({page['browser_threads_niced'][0]} of {page['browser_threads_niced'][1]} threads "
        "at it before the last). Statistics over the ticks that removed bone.",
        "",
        "| mode | samples | lost | cutting share | p50 µs | p99 µs | p99.9 µs | max µs "
        "| chromium CPU % | stack CPU % | hot loop CPU % |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in (closed, opened):
        lines.append(f"| {r['mode']} | {r['samples']} | {r['lost']} | "
                     f"{r['cutting_fraction']:.2f} | {r['p50_us']:.0f} | {r['p99_us']:.0f} | "
                     f"{r['p999_us']:.0f} | {r['max_us']:.0f} | {r['browser_cpu_pct']:.0f} | "
                     f"{r['stack_cpu_pct']:.0f} | {r['hot_loop_cpu_pct']:.0f} |")
    lines += [
        "",
        "CPU: utime + stime over the chunks' wall time, % of one core (chromium: its whole "
        "process tree; stack: the process serving REST and the WebSockets; hot loop: the "
        f"session's UDP loop). During the open chunks ({wall:.1f} s; closed: "
        f"{closed['wall_s']:.1f} s) the page drew {opened['frames']} frames "
        f"({opened['frames'] / wall:.1f}/s), received {opened['telemetry_samples']} telemetry "
        f"samples ({opened['telemetry_samples'] / wall:.1f}/s) and {opened['mesh_updates']} "
        f"mesh updates ({opened['mesh_updates'] / wall:.1f}/s); playwright's driver used "
        f"{opened['driver_cpu_pct']:.1f} %. Round trip p50 {opened['p50_us']:.0f} µs open "
        f"against {closed['p50_us']:.0f} µs closed, p99 {opened['p99_us']:.0f} against "
        f"{closed['p99_us']:.0f} µs, p99.9 {opened['p999_us']:.0f} against "
        f"{closed['p999_us']:.0f} µs.",
    ]
    if page.get("page_errors"):
        lines += ["", f"The page reported errors: {page['page_errors']}"]
    return lines


if __name__ == "__main__":
    sys.exit(_serve(float(sys.argv[1]), Path(sys.argv[2])))
