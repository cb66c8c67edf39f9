"""``python -m benchmarks.container [--out benchmarks]``, from a checkout's root (the project's
own measurement: it needs podman): the server image built with podman, its size and build time, and
the round trip through it beside the bare process's, in one run.

Three servers on this machine, each ``burrforce serve`` cutting the thesis's workpiece
(phantom:workpiece at 0.1 mm, one hot-loop worker, si_mm):

- ``bare``: the process, as ``pip install`` gives it;
- ``container, host network``: the image run with ``--network host`` (the README's lowest
  latency setting: no NAT between the engine and the hot loop);
- ``container, published ports``: the image with its ports published on 127.0.0.1, as
  docker/compose.yaml runs it (the kernel's NAT or podman's port forwarder on the way).

The client is ``bench latency``'s: the same raster of grooves at 3 mm/s, 60 000 rpm, paced
at 1 kHz, samples interleaved in chunks across the three servers so the machine's slow
spells fall on all of them alike; statistics over the ticks that removed bone. Hot loops on
the last CPU, the client on the first, as in ``bench latency``.
"""

from __future__ import annotations

import argparse
import gc
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

import httpx
import numpy as np

from burrforce.server.argtypes import int_in
from burrforce.server.bench import runner
from burrforce.server.bench.latency import CHUNK, GrooveCut, StreamClient, pin_cpus, run_stats
from burrforce.server.bench.serve_process import spawn_serve
from support.podman import HTTP_PORT, UDP_PORT, Podman, PodmanError, free_port

from . import ROOT

TAG = "localhost/burrforce:bench"
TOKEN = "bench-container-token-0123456789"
SERVE_ENV = {"BURRFORCE_BONE": "phantom:workpiece", "BURRFORCE_VOXEL_MM": "0.1",
             "BURRFORCE_FRAME": "si_mm", "BURRFORCE_WORKERS": "1"}
TARGETS = ("bare", "container, host network", "container, published ports")


def _host_pid(podman: Podman, name: str, pid_in_container: int) -> int:
    """The host's pid of a process the container knows by ``pid_in_container``."""
    out = podman("top", name, "pid", "hpid").stdout.split("\n")[1:]
    for line in out:
        fields = line.split()
        if len(fields) == 2 and int(fields[0]) == pid_in_container:
            return int(fields[1])
    raise PodmanError(f"no process {pid_in_container} in {name}: {out}")


def _loop_pid(http: str) -> int:
    return int(httpx.get(f"{http}/v1/health", timeout=5.0).json()["workers"][0]["pid"])


def _session(podman: Podman, name: str, folder: Path) -> tuple[int, bytes]:
    """The default session's id and key, from the connection file serve wrote inside."""
    path = folder / f"{name}.json"
    podman("cp", f"{name}:/tmp/burrforce-connection.json", str(path))
    c = json.loads(path.read_text())
    return int(c["session"]), bytes.fromhex(c["key_hex"])


def run(samples: int, build: bool = True, progress=None) -> dict:
    say = progress or (lambda text: None)
    if not (ROOT / "docker" / "Dockerfile").exists():
        raise RuntimeError(f"no docker/Dockerfile under {ROOT}")
    folder = Path(tempfile.mkdtemp(prefix="burrforce-bench-container-"))
    podman = Podman(folder / "podman")
    reason = podman.unavailable()
    if reason is not None:
        raise RuntimeError(reason)
    version = podman("--version").stdout.strip()
    base, base_s = podman.base_image(progress=say)
    build_s = None
    if build or not podman.image_exists(TAG):
        say("building the image, every layer anew (podman build --no-cache)")
        build_s = podman.build(TAG, ROOT, base, layer_cache=False)
    size_mb = podman.image_size_bytes(TAG) / 1e6
    base_mb = podman.image_size_bytes(base) / 1e6
    boxes = []
    bare = None
    try:
        say("starting the bare server and two containers")
        bare = spawn_serve(folder / "bare", "--workers", "1", env=SERVE_ENV)
        bare_http = bare.connection.http_url
        host_udp, host_http = free_port(), free_port(socket.SOCK_STREAM)
        nat_udp, nat_http = free_port(), free_port(socket.SOCK_STREAM)
        env = {**SERVE_ENV, "BURRFORCE_TOKEN": TOKEN}
        specs = (
            ("burrforce-bench-host", {**env, "BURRFORCE_UDP_PORT": str(host_udp),
                                      "BURRFORCE_HTTP_PORT": str(host_http)}, (), "host",
             host_udp, host_http),
            ("burrforce-bench-nat", env, (f"127.0.0.1:{nat_udp}:{UDP_PORT}/udp",
                                          f"127.0.0.1:{nat_http}:{HTTP_PORT}/tcp"), None,
             nat_udp, nat_http),
        )
        ready = {}
        for name, box_env, publish, network, _, http_port in specs:
            t0 = time.monotonic()
            box = podman.run(TAG, name, env=box_env, publish=publish, network=network)
            boxes.append(box)
            box.wait_http(f"http://127.0.0.1:{http_port}/v1/health", timeout_s=180)
            ready[name] = time.monotonic() - t0
        key_bare = bytes.fromhex(bare.connection.key_hex or "")
        clients = {"bare": StreamClient((bare.connection.host, bare.connection.udp_port),
                                   bare.connection.session, key_bare, GrooveCut())}
        for (name, _, _, _, udp, _), target in zip(specs, TARGETS[1:], strict=True):
            session, key = _session(podman, name, folder)
            clients[target] = StreamClient(("127.0.0.1", udp), session, key, GrooveCut())
        pids = [_loop_pid(bare_http)] + [
            _host_pid(podman, spec[0], _loop_pid(f"http://127.0.0.1:{spec[5]}"))
            for spec in specs]
        placement = pin_cpus(*pids)
        gc.collect()
        gc.freeze()
        done = 0
        while done < samples:
            n = min(CHUNK, samples - done)
            for target in TARGETS:
                clients[target].chunk(n, 0.001)
            done += n
            say(f"1 kHz: {done}/{samples}")
        runs = []
        for target in TARGETS:
            c = clients[target]
            mask = np.array(c.cutting, dtype=bool)
            rtt = np.array(c.rtt_us)[mask]
            runs.append(asdict(run_stats(target, "1 kHz", rtt, c.lost,
                                      float(mask.mean()) if len(mask) else 0.0)))
    finally:
        for box in boxes:
            box.remove()
        if bare is not None:
            bare.stop()
        shutil.rmtree(folder, ignore_errors=True)
    return {
        "image": TAG, "image_mb": size_mb, "base": base, "base_mb": base_mb,
        "base_seconds": base_s, "build_seconds": build_s,
        "container_ready_seconds": ready, "samples": samples, "placement": placement,
        "podman": version, "runs": runs,
    }


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, json_path = runner.save_json(out, "container", result)
    stamp = result["date"]
    runs = {r["mode"]: r for r in result["runs"]}
    bare = runs["bare"]["p50_us"]
    build = (f"{result['build_seconds']:.0f} s" if result["build_seconds"] is not None
             else "not rebuilt in this run")
    lines = [
        "# The server image (`python -m benchmarks.container`)",
        "",
        f"{stamp}; {result['machine']}; {result['podman']}. One run.",
        "",
        f"- Image `{result['image']}`: {result['image_mb']:.0f} MB on disk (all layers, "
        f"uncompressed), of which the base `{result['base']}` {result['base_mb']:.0f} MB. "
        f"Build (`podman build --no-cache`: every layer, the dependencies' included, with "
        f"pip's download cache warm; kernels compiled): {build}.",
        "- From `podman run` to health 200: "
        + "; ".join(f"{k} {v:.1f} s" for k, v in result["container_ready_seconds"].items())
        + " (the kernels load from the image's cache).",
        "",
        "Round trips while cutting the workpiece (0.1 mm voxels, α = 60°, 0.5 mm deep, "
        f"3 mm/s, 60 000 rpm), paced at 1 kHz, chunks of {CHUNK} interleaved across the "
        f"servers; over the ticks that removed bone. Placement: {result['placement']}.",
        "",
        "| server | samples | lost | p50 µs | p99 µs | p99.9 µs | max µs | p50 − bare µs |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["runs"]:
        lines.append(f"| {r['mode']} | {r['samples']} | {r['lost']} | {r['p50_us']:.0f} | "
                     f"{r['p99_us']:.0f} | {r['p999_us']:.0f} | {r['max_us']:.0f} | "
                     f"{r['p50_us'] - bare:+.0f} |")
    lines.append("")
    md_path = out / "container.md"
    md_path.write_text("\n".join(lines))
    return md_path, json_path


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "container", main,
        help="the server image: size, build time, round trip against the bare process",
        description="Build docker/Dockerfile with podman (from a local Debian base made with "
                    "mmdebstrap: no registry), then measure round trips while cutting through "
                    "the bare process, the container on the host network and the container "
                    "with published ports, interleaved. Needs podman (and mmdebstrap for the "
                    "base) and a source checkout. Writes OUT/container.md and container.json.")
    p.add_argument("--samples", type=int_in(500, 10_000_000, "sample count"), default=10_000,
                   help="round trips per server at 1 kHz. Default 10000")
    p.add_argument("--no-build", action="store_true",
                   help="reuse the image a previous run built (build time not measured)")


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    try:
        result = run(args.samples, build=not args.no_build, progress=runner.say)
    except (RuntimeError, PodmanError, subprocess.SubprocessError) as exc:
        print(f"python -m benchmarks.container: {exc}", file=sys.stderr)
        return 1
    return runner.report(args, *write_results(result, out))


if __name__ == "__main__":
    raise SystemExit(runner.run_alone(add_parser, "container",
                                      prog="python -m benchmarks.container"))
