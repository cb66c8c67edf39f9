"""``burrforce bench startup``: how long ``burrforce serve`` takes to be ready, with an empty
numba cache (the first start: it compiles) and with a warm one (every later start).

Ready means all three: the banner printed, REST ``/v1/health`` answering 200 and the hot loop
answering a UDP pose (plain ``serve``; with ``--demo`` the demo streams the session itself,
so only the first two). Each run is a real ``burrforce serve`` in a subprocess on free
loopback ports with a fresh data directory; every run of a case shares one cache directory,
which starts empty. NUMBA_DEBUG_CACHE counts what each run compiled ("data saved") and
loaded: a warm run must save nothing.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

from ...client.udp import BurrClient
from . import runner
from .procstat import cpu_s
from .serve_process import spawn_serve

#: (name, serve arguments).
CASES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("serve", ()),
    ("serve --demo", ("--demo",)),
)
READY_TIMEOUT_S = 300.0


def _health(url: str, deadline: float) -> None:
    while True:
        try:
            if httpx.get(f"{url}/v1/health", timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        if time.monotonic() > deadline:
            raise RuntimeError(f"{url}/v1/health did not answer 200")
        time.sleep(0.01)


def _udp(host: str, port: int, session: int, key: str | None, deadline: float) -> None:
    with BurrClient(host, port, session, key, timeout_s=0.5) as client:
        while True:
            try:
                client.exchange((0.0, 0.0, 100.0))  # far above the bone: nothing is cut
                return
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the hot loop on {host}:{port} did not answer") \
                        from None


def _cpu_s(pid: int) -> float | None:
    """CPU seconds (user + system) used so far by ``pid`` and its descendants still alive;
    None where /proc cannot tell (not Linux). Unlike wall time, not inflated by other work
    on a busy machine."""
    total = cpu_s(pid)
    if total is None:
        return None
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                for child in f.read().split():
                    total += _cpu_s(int(child)) or 0.0
        return total
    except (OSError, ValueError, IndexError):
        return None


def start_once(folder: Path, cache_dir: Path, args: tuple[str, ...], udp: bool,
               home: Path | None = None) -> dict:
    """One ``serve`` from launch to ready, then stopped. Seconds since the launch, and the
    CPU seconds its processes had used by then. ``home``: a HOME of its own (a new user's:
    no token, no data, no cache of any kind)."""
    env = {"NUMBA_CACHE_DIR": str(cache_dir), "NUMBA_DEBUG_CACHE": "1"}
    if home is not None:
        home.mkdir(parents=True, exist_ok=True)
        env.update(HOME=str(home), XDG_CACHE_HOME="", XDG_DATA_HOME="", XDG_CONFIG_HOME="")
    t0 = time.monotonic()
    serve = spawn_serve(folder, *args, timeout_s=READY_TIMEOUT_S, env=env)
    try:
        banner_s = time.monotonic() - t0
        c = serve.connection
        deadline = time.monotonic() + READY_TIMEOUT_S
        _health(c.http_url, deadline)
        if udp:
            _udp(c.host, c.udp_port, c.session, c.key_hex, deadline)
        ready_s = time.monotonic() - t0
        cpu_s = _cpu_s(serve.proc.pid)
    finally:
        _, after = serve.stop()
    printed = serve.banner + after
    return {"banner_s": banner_s, "ready_s": ready_s, "cpu_s": cpu_s,
            # Counted over the whole run: the spare's warm-up after "ready" counts too.
            "kernels_saved": printed.count("[cache] data saved"),
            "kernels_loaded": printed.count("[cache] data loaded")}


def fill_cache(cache_dir: Path) -> None:
    """``burrforce compile`` into ``cache_dir``: what every start after the first finds."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    env.pop("NUMBA_DEBUG_CACHE", None)
    subprocess.run([sys.executable, "-m", "burrforce.server.cli", "compile", "--quiet"],
                   env=env, check=True, stdout=subprocess.DEVNULL, timeout=1800)


def run(runs: int = 5, cold: bool = True, progress=print,
        cache_dir: Path | None = None, cold_runs: int = 3) -> dict:
    """Per case, ``cold_runs`` first starts (each a new empty cache and a new HOME: the
    server compiles what its session needs and is timed until ready), then ``runs`` starts
    on a cache ``burrforce compile`` filled (``cache_dir`` as it is, if given: warm runs
    only)."""
    results = []
    cold = cold and cache_dir is None and cold_runs > 0
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        warm_cache = cache_dir
        if warm_cache is None:
            warm_cache = Path(tmp) / "numba-compiled"
            progress("filling a cache with `burrforce compile` for the warm starts")
            fill_cache(warm_cache)
        for name, args in CASES:
            case = {"case": name, "cold": None, "cold_runs": [], "warm": []}
            for i in range(cold_runs if cold else 0):
                run_dir = Path(tmp) / f"cold{i}"
                r = start_once(run_dir / "serve", run_dir / "numba-cache", args,
                               udp=not args, home=run_dir / "home")
                shutil.rmtree(run_dir, ignore_errors=True)
                progress(f"{name} cold: ready in {r['ready_s']:.2f} s (banner "
                         f"{r['banner_s']:.2f} s, CPU {r['cpu_s'] or 0:.2f} s), kernels saved "
                         f"{r['kernels_saved']}")
                case["cold_runs"].append(r)
            for i in range(runs):
                folder = Path(tmp) / f"run{i}"
                r = start_once(folder, warm_cache, args, udp=not args)
                shutil.rmtree(folder, ignore_errors=True)
                progress(f"{name} warm: ready in {r['ready_s']:.2f} s (banner "
                         f"{r['banner_s']:.2f} s, CPU {r['cpu_s'] or 0:.2f} s), kernels saved "
                         f"{r['kernels_saved']}, loaded {r['kernels_loaded']}")
                case["warm"].append(r)
            colds = case["cold_runs"]
            if colds:
                case["cold"] = sorted(colds, key=lambda r: r["ready_s"])[len(colds) // 2]
            case["cold_ready_s"] = (statistics.median(r["ready_s"] for r in colds)
                                    if colds else None)
            ready = [r["ready_s"] for r in case["warm"]]
            case["warm_ready_s"] = statistics.median(ready)
            case["warm_ready_s_median"] = case["warm_ready_s"]
            case["warm_ready_s_min"] = min(ready)
            case["warm_ready_s_max"] = max(ready)
            case["warm_kernels_saved"] = sum(r["kernels_saved"] for r in case["warm"])
            cpu = [r["cpu_s"] for r in case["warm"] if r["cpu_s"] is not None]
            case["warm_cpu_s_median"] = statistics.median(cpu) if cpu else None
            results.append(case)
    return {"cases": results, "runs": runs, "cold_runs": cold_runs if cold else 0,
            "python": sys.executable}


def write_results(result: dict, out: Path, note: str = "") -> tuple[Path, Path]:
    result, js = runner.save_json(out, "startup", result)
    stamp = result["date"]
    lines = [
        "# Start-up (`burrforce bench startup`)", "",
        f"{stamp}; {result['machine']}; {result['python']}.", "",
        "Seconds from launching `burrforce serve` (default bone phantom:temporal, free "
        "loopback ports, a new data directory) until it is ready: banner printed, "
        "`/v1/health` 200 and, for plain `serve`, a UDP pose answered. Cold: a new user's "
        "first start — an empty numba cache and an empty HOME, so the server compiles what "
        f"its session needs first (median of {result['cold_runs']} runs; the rest compiles "
        "behind the running server); warm: a cache `burrforce compile` filled (median of "
        f"{result['runs']} runs). Kernels saved: numba cache entries written "
        "(`NUMBA_DEBUG_CACHE`) over the whole run: a warm start must write none. CPU s: user "
        "+ system seconds the server's processes had used when ready (robust to a busy "
        "machine, unlike the wall times).", "",
        "| case | cold ready s median | cold kernels saved | warm ready s median | min | max "
        "| warm CPU s median | warm kernels saved |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for c in result["cases"]:
        cold = c["cold"] or {}
        cold_s = f"{c['cold_ready_s']:.1f}" if c.get("cold_ready_s") is not None else ""
        cpu = c["warm_cpu_s_median"]
        cpu_s = "" if cpu is None else f"{cpu:.2f}"
        lines.append(
            f"| `{c['case']}` | {cold_s} | {cold.get('kernels_saved', '')} | "
            f"{c['warm_ready_s_median']:.2f} | {c['warm_ready_s_min']:.2f} | "
            f"{c['warm_ready_s_max']:.2f} | "
            f"{cpu_s} | "
            f"{c['warm_kernels_saved']} |")
    if note:
        lines += ["", note]
    return runner.write_page(out, "startup", lines), js


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "startup", main,
        help="time to ready of serve: first start (empty numba cache) and later",
        json_help=runner.JSON_ROWS,
        description="Start `burrforce serve` and `serve --demo` as a new user does (an "
                    "empty numba cache and an empty HOME) COLD_RUNS times, then RUNS times on "
                    "a cache `burrforce compile` filled, and time each until it is ready "
                    "(banner, /v1/health, a UDP pose answered). Rows carry cold_ready_s and "
                    "warm_ready_s (medians). Writes OUT/startup.md and startup.json.")
    p.add_argument("--runs", type=int, default=5, help="warm starts per case. Default 5")
    p.add_argument("--cold-runs", type=int, default=3,
                   help="first starts per case, each on a new empty cache. Default 3")
    p.add_argument("--no-cold", action="store_true",
                   help="skip the first starts (warm starts only)")
    p.add_argument("--cache-dir", type=Path, default=None,
                   help="time warm starts only, on this numba cache as it is (e.g. filled by "
                        "`burrforce compile`) instead of a new empty one")
    p.add_argument("--note", default="", help="a paragraph appended to startup.md")


def main(args: argparse.Namespace) -> int:
    if args.runs < 1 or args.cold_runs < 0:
        raise ValueError("--runs must be at least 1 and --cold-runs at least 0")
    out = runner.out_dir(args)
    result = run(args.runs, not args.no_cold, runner.say, args.cache_dir, args.cold_runs)
    rows = [{"case": c["case"], "cold_ready_s": c["cold_ready_s"],
             "warm_ready_s": c["warm_ready_s"], "cold_runs": len(c["cold_runs"]),
             "warm_runs": len(c["warm"]), "warm_kernels_saved": c["warm_kernels_saved"]}
            for c in result["cases"]]
    return runner.report(args, *write_results(result, out, args.note), rows=rows)
