"""``burrforce bench load-while-streaming``: one session's round trips while another loads a
large bone.

As ``burrforce serve`` runs it: a streaming client (a process of its own, like an engine)
cuts the workpiece at 1 kHz in one session, while this process, playing the control plane,
loads a size³ bone into a second session again and again — :func:`bone.shared.publish` (the
loading worker's part) then ``add_session``/``replace_session`` (the hot loop's part: mapping
the file, building the engine and the session, warming it). The streaming session's round
trips are split by when their packet was sent: during a load (publish and hot-loop build),
during the hot-loop build alone, and outside any load.

With ``--file`` (and ``--synthetic``), the real thing instead: ``burrforce serve`` runs with
the workpiece in session 1, the client streams it, and each file is uploaded and loaded into
session 2 over REST, as a client would (``load_files``); the report gives each load's answer,
time and the control plane's peak resident memory, and the replies lost meanwhile.

Wall-clock round trips: on a shared machine, run it when it is quiet, or compare runs made
back to back.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ...proto.tag import new_key
from ..argtypes import float_in, int_in
from . import runner
from .timing import wait_until

STREAM_SESSION = 1
LOAD_SESSION = 2
DEFAULT_SIZE = 512
#: Round trips sent within this of a load's end still count as during it (the old bone's
#: memory goes, the new session's first packets): s.
TAIL_S = 0.2


def _stats(rtt_us: np.ndarray) -> dict[str, float | int]:
    if len(rtt_us) == 0:
        return {"samples": 0}
    return {"samples": len(rtt_us), "p50_us": float(np.median(rtt_us)),
            "p99_us": float(np.percentile(rtt_us, 99)), "max_us": float(rtt_us.max())}


# -- the streaming client (its own process) ----------------------------------------------------
def stream(host: str, port: int, key: bytes, seconds: float, rate_hz: float,
           out: Path) -> None:
    """Cut the workpiece at ``rate_hz`` until SIGTERM (or for ``seconds``); save (send time
    ns monotonic, round trip µs or NaN for a lost packet) to ``out`` (.npy, shape (n, 2))."""
    import gc
    import signal

    from .latency import GrooveCut, StreamClient

    stopped = []
    signal.signal(signal.SIGTERM, lambda *_: stopped.append(True))
    client = StreamClient((host, port), STREAM_SESSION, key, GrooveCut())
    client.chunk(1, None)  # untimed: whatever the protocol asks before a stream
    gc.collect()
    gc.freeze()  # the client's own collector must not show up as server latency
    period = 1.0 / rate_hz
    rows = np.empty((int(seconds * rate_hz) + 1, 2), dtype=np.float64)
    clock = time.monotonic_ns
    due = time.perf_counter()
    i = 0
    while i < len(rows) and not stopped:
        due += period
        wait_until(due)
        t0 = clock()
        client.sock.send(client.datagram(t0 // 1000, i == 0))
        rtt = float("nan")
        try:
            data = client.sock.recv(2048)
            while not client.is_reply(data):
                data = client.sock.recv(2048)
            rtt = (clock() - t0) / 1e3
        except OSError:  # lost (a timeout), or the loop is gone
            pass
        rows[i] = (t0, rtt)
        i += 1
    np.save(out, rows[:i])


# -- the control plane's part (this process) ---------------------------------------------------
def run(size: int, loads: int, quiet_s: float, rate_hz: float = 1000.0, progress=None) -> dict:
    from ..bone.shared import SharedBone, publish, run_directory
    from ..hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec
    from .latency import pin_cpus
    from .load import build_bone

    say = progress or (lambda text: None)
    say(f"building the {size}³ bone")
    bone = build_bone(size)
    key = new_key()
    shared = run_directory(3 * bone.grid.density.size * 4)
    workdir = Path(tempfile.mkdtemp(prefix="burrforce-lws-"))
    try:
        from ..bone import phantom

        workpiece = publish(phantom("workpiece", 0.1), shared, "stream.bone")
        hot = HotLoopProcess(HotLoopConfig(sessions=(
            SessionSpec(STREAM_SESSION, workpiece, None, key, SessionConfig()),)))
        say("starting the hot loop")
        host, port = hot.start()
        try:
            placement = pin_cpus(hot.pid)
            Path(workpiece.path).unlink()
            # At most: the client is stopped once the last quiet spell is over.
            budget_s = quiet_s * (loads + 2) + loads * 120.0
            samples = workdir / "rtt.npy"
            client = subprocess.Popen(
                [sys.executable, "-m", "burrforce.server.bench.load_while_streaming",
                 host, str(port), key.hex(), str(budget_s), str(rate_hz), str(samples)])
            cpus = sorted(os.sched_getaffinity(0))
            if len(cpus) > 1:
                try:
                    os.sched_setaffinity(client.pid, {cpus[0]})
                except OSError:
                    pass
            windows = []
            reader = None
            time.sleep(quiet_s + 1.0)  # the client's start-up, then a quiet spell
            for n in range(loads):
                say(f"load {n + 1}/{loads}: publishing")
                t_publish = time.monotonic_ns()
                ref = publish(bone, shared, f"load-{n}.bone")
                # As the control plane: it maps the bone it serves, and unmaps the old one
                # after the swap, so the old file's memory is freed here, not in the loop.
                old, reader = reader, SharedBone(ref)
                t_call = time.monotonic_ns()
                say(f"load {n + 1}/{loads}: building the session in the hot loop")
                hot.call("add_session" if n == 0 else "replace_session",
                         spec=SessionSpec(LOAD_SESSION, ref, None, key, SessionConfig(),
                                          materials=bone.materials))
                t_end = time.monotonic_ns()
                Path(ref.path).unlink()
                if old is not None:
                    old.close()
                    del old
                windows.append((t_publish, t_call, t_end))
                time.sleep(quiet_s)
            client.terminate()
            client.wait()
            server = hot.stats()
        finally:
            hot.stop()
        rows = np.load(samples)
    finally:
        shutil.rmtree(shared, ignore_errors=True)
        shutil.rmtree(workdir, ignore_errors=True)
    sent, rtt = rows[:, 0], rows[:, 1]
    tail_ns = TAIL_S * 1e9
    during = np.zeros(len(sent), dtype=bool)
    publishing = np.zeros(len(sent), dtype=bool)
    building = np.zeros(len(sent), dtype=bool)
    after = np.zeros(len(sent), dtype=bool)
    near = np.zeros(len(sent), dtype=bool)
    worst = []
    for t_publish, t_call, t_end in windows:
        this = (sent >= t_publish) & (sent <= t_end + tail_ns)
        during |= this
        publishing |= (sent >= t_publish) & (sent < t_call)
        building |= (sent >= t_call) & (sent <= t_end)
        after |= (sent > t_end) & (sent <= t_end + tail_ns)
        near |= (sent >= t_publish - tail_ns) & (sent <= t_end + 2 * tail_ns)
        worst.append(round(float(np.nanmax(rtt[this], initial=0.0))))
    # Outside: from the first load's quiet spell on (the first second is the client's start).
    outside = ~near & (sent >= windows[0][0] - quiet_s * 1e9)
    lost = np.isnan(rtt)
    ok = ~lost
    return {
        "size": size,
        "loads": loads,
        "rate_hz": rate_hz,
        "placement": placement,
        "publish_s": [round((c - p) / 1e9, 3) for p, c, _ in windows],
        "hot_loop_build_s": [round((e - c) / 1e9, 3) for _, c, e in windows],
        "during_load": _stats(rtt[during & ok]) | {"lost": int((during & lost).sum())},
        "during_publish": _stats(rtt[publishing & ok])
        | {"lost": int((publishing & lost).sum())},
        "max_per_load_us": worst,
        "during_build": _stats(rtt[building & ok]) | {"lost": int((building & lost).sum())},
        "after_swap": _stats(rtt[after & ok]) | {"lost": int((after & lost).sum())},
        "outside": _stats(rtt[outside & ok]) | {"lost": int((outside & lost).sum())},
        "server_counters": server["counters"],
    }


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, json_path = runner.save_json(out, "load-while-streaming", result)
    stamp = result["date"]

    def row(name: str, s: dict) -> str:
        if not s["samples"]:
            return f"| {name} | 0 | {s['lost']} | – | – | – |"
        return (f"| {name} | {s['samples']} | {s['lost']} | {s['p50_us']:.0f} | "
                f"{s['p99_us']:.0f} | {s['max_us']:.0f} |")

    lines = [
        "# Round trips while another session loads a bone (`burrforce bench "
        "load-while-streaming`)",
        "",
        f"{stamp}; {result['machine']}. One session cuts the workpiece (0.1 mm voxels) at "
        f"{result['rate_hz']:g} Hz from a client process of its own; meanwhile a "
        f"{result['size']}³ bone is loaded into a second session {result['loads']} times "
        "(publish to shared memory as the control plane's loading worker does, then "
        "add_session/replace_session in the hot loop). Round trips by when their packet was "
        f"sent: during a load (publish to the session's swap, plus {TAIL_S:g} s), split "
        "into the control plane's publish, the hot loop's build (the add/replace_session "
        f"call) and the {TAIL_S:g} s after the swap (the control plane unmaps the old "
        "bone, which frees its memory); and outside any load. Placement: "
        f"{result['placement']}.",
        "",
        "| streaming session | samples | lost | p50 µs | p99 µs | max µs |",
        "|---|---:|---:|---:|---:|---:|",
        row("during a load", result["during_load"]),
        row("during the control plane's publish", result["during_publish"]),
        row("during the hot loop's build", result["during_build"]),
        row(f"after the swap ({TAIL_S:g} s)", result["after_swap"]),
        row("outside loads", result["outside"]),
        "",
        f"Publish (control plane) per load, s: {result['publish_s']}; hot-loop build "
        f"(add/replace_session call), s: {result['hot_loop_build_s']}; worst round trip "
        f"per load, µs: {result['max_per_load_us']}.",
        "",
        f"Server counters: {json.dumps(result['server_counters'])}",
    ]
    return runner.write_page(out, "load-while-streaming", lines), json_path


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "load-while-streaming", main,
        help="a streaming session's round trips while another session loads a large bone",
        description="Stream one session at 1 kHz (cutting) while a size³ bone is loaded "
                    "into another session, and report the streaming session's round trips "
                    "during and outside the loads. Writes OUT/load-while-streaming.md and "
                    ".json.", json_help=runner.RESULTS_JSON)
    p.add_argument("--size", type=int_in(64, 1024, "grid size"), default=DEFAULT_SIZE,
                   help=f"the loaded bone is size³ voxels. Default {DEFAULT_SIZE}")
    p.add_argument("--loads", type=int_in(1, 100, "load count"), default=3,
                   help="loads into the second session (the first adds it, the others "
                        "replace its bone). Default 3")
    p.add_argument("--quiet-s", type=float_in(0.5, 600.0, "quiet spell", "s"), default=3.0,
                   help="seconds of streaming before, between and after the loads. "
                        "Default 3")
    p.add_argument("--file", type=Path, action="append", default=[], metavar="PATH",
                   help="instead of --size: run burrforce serve and upload and load this "
                        "bone file into a second session, measuring the control plane's "
                        "peak memory (repeat for several; a name starting bomb- loads as "
                        "density, any other as ct). Writes OUT/load-while-streaming-files.md "
                        "and .json")
    p.add_argument("--synthetic", action="store_true",
                   help="as --file, with generated files: float64 CTs of 512³ and 1024³ "
                        "voxels and 8 GiB uint8 gzip bombs, as gzip NRRD and .nii.gz (a few "
                        "MB each; writing them takes a minute)")
    p.add_argument("--load-budget", type=size_bytes, default=None, metavar="SIZE",
                   help="with --file or --synthetic: serve's load_budget_bytes (2GiB, 800M). "
                        "Default serve's: each load's bone + 512 MiB")


def size_bytes(text: str) -> int:
    from ..api.config import parse_size_bytes

    try:
        return parse_size_bytes(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    if args.file or args.synthetic:
        return _main_files(args, out)
    result = run(args.size, args.loads, args.quiet_s, progress=runner.say)
    md, js = write_results(result, out)
    return runner.report(args, md, js, rows=result)


def _main_files(args: argparse.Namespace, out: Path) -> int:
    from .load_files import page_lines, run_files, synthetic_files

    work = Path(tempfile.mkdtemp(prefix="burrforce-lws-files-"))
    try:
        paths = list(args.file)
        if args.synthetic:
            runner.say("writing the synthetic files")
            paths += synthetic_files(work)
        result = run_files(paths, args.quiet_s, load_budget=args.load_budget,
                           progress=runner.say)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result, js = runner.save_json(out, "load-while-streaming-files", result)
    md = runner.write_page(out, "load-while-streaming-files", page_lines(result))
    return runner.report(args, md, js, rows=result)


if __name__ == "__main__":  # the streaming client: host port key-hex seconds rate-hz out.npy
    _host, _port, _key, _seconds, _rate, _out = sys.argv[1:7]
    stream(_host, int(_port), bytes.fromhex(_key), float(_seconds), float(_rate), Path(_out))
