"""``burrforce bench mesh``: the carved bone as chunk meshes (``proto/MESH.md``): what a chunk
size costs, and how fast an engine's copy follows the cut over the WebSocket against REST
polling, and what a UDP side stream would have to carry.

Offline, per bone and ``chunk_bricks``: the whole surface (bytes, chunks, triangles, time to
mesh), then a groove cut tick by tick (the thesis's cut: 5 mm/s, 60 000 rpm, 0.5 mm deep, the
tool tilted 60°) with an update made every 33 ticks, as the push channel does at its default
33 ms (bytes, chunks, time to mesh per update).

Live, one run each: ``burrforce serve`` in its own process, the Python client streaming the
groove at 1 kHz, and in a third process an engine-side copy kept by the WebSocket
(``interval_ms`` 33) or by REST polls every 33 ms (a 30 Hz engine frame). Latency: from each
REPLY that announced a new ``bone_version`` arriving, to the copy holding that version.
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from . import runner
from .serve_process import spawn_serve

CHUNK_BRICKS = (1, 2, 4, 8)
BONES = (("workpiece", 0.1), ("temporal", 0.2))
UPDATE_TICKS = 33
TOKEN = "bench-mesh-token-0123456789"
#: The largest UDP payload that is not fragmented on a 1500-byte Ethernet MTU (IPv4).
UDP_PAYLOAD = 1472


def _groove_ticks(surface_z_mm: float, x0: float, y0: float, length_mm: float = 6.0):
    """(centre, feed) per 1 ms tick of the thesis's cut along +x."""
    a = math.radians(60.0)
    axis = np.array([-math.cos(a), 0.0, math.sin(a)])
    z = surface_z_mm + 2.0 - 0.5
    feed = np.array([5.0, 0.0, 0.0])
    for i in range(int(length_mm / 5.0 * 1000)):
        yield np.array([x0 + 0.005 * i, y0, z]), axis, feed


def offline(bone_name: str, voxel_mm: float, chunk_bricks: int) -> dict:
    """The whole surface and a groove's updates for one bone and chunk size."""
    from ...proto.mesh_chunks import encode
    from ..api.mesh_pages import MAX_BYTES_MAX, MeshRequest, mesh_page
    from ..bone import BoneEngine, ShaftParams, phantom

    bone = phantom(bone_name, voxel_mm)
    grid = bone.grid
    req = MeshRequest(1, chunk_bricks, True, False, "unity")
    t = time.perf_counter()
    full = mesh_page(grid, req, None, 0, MAX_BYTES_MAX)
    full_s = time.perf_counter() - t
    full_bytes = len(encode(full))
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))
    lo, hi = grid.bounds_mm()
    x0, y0 = 0.3 * lo[0] + 0.7 * (lo[0] + hi[0]) / 2 if bone_name == "temporal" else 3.0, 0.0
    have = grid.version
    sizes, chunks, times = [], [], []
    for i, (centre, axis, feed) in enumerate(_groove_ticks(0.0, x0, y0)):
        engine.step(centre, axis, feed, 60_000.0)
        if (i + 1) % UPDATE_TICKS == 0 and grid.version != have:
            t = time.perf_counter()
            page = mesh_page(grid, req, have, 0, MAX_BYTES_MAX)
            times.append(time.perf_counter() - t)
            sizes.append(len(encode(page)))
            chunks.append(len(page.chunks))
            have = page.bone_version
    sizes_a = np.array(sizes or [0])
    return {
        "bone": bone_name, "voxel_mm": voxel_mm, "chunk_bricks": chunk_bricks,
        "chunk_mm": round(8 * chunk_bricks * voxel_mm, 3),
        "full_chunks": len(full.chunks),
        "full_triangles": int(sum(len(c.triangles) for c in full.chunks)),
        "full_bytes": full_bytes, "full_ms": 1e3 * full_s,
        "updates": len(sizes),
        "update_bytes_p50": float(np.median(sizes_a)),
        "update_bytes_max": int(sizes_a.max()),
        "update_chunks_p50": float(np.median(chunks or [0])),
        "update_ms_p50": 1e3 * float(np.median(times or [0.0])),
        "update_ms_max": 1e3 * float(max(times or [0.0])),
        "update_datagrams_p50": float(np.median(np.ceil(sizes_a / UDP_PAYLOAD))),
    }


def _follow(mode: str, url: str, session: int, stop, out) -> None:
    """In its own process (no GIL shared with the 1 kHz sender, as in an engine): keep a copy
    by ``mode`` until ``stop``; put [(monotonic time, version held)] on ``out``."""
    from ...client.mesh import ChunkedMesh, sync_rest, watch
    from ...client.rest import BurrRest

    api = BurrRest(url, TOKEN)
    copy = ChunkedMesh()
    sync_rest(api, session, copy, frame="server")  # the initial copy, not timed
    got: list[tuple[float, int]] = [(time.monotonic(), copy.have)]
    if mode == "ws":
        it = watch(url, TOKEN, session, since=copy.have, interval_ms=33, frame="server")
        for m in it:
            if copy.apply(m):
                got.append((time.monotonic(), copy.have))
            if stop.is_set():
                it.close()
                break
    else:
        while not stop.is_set():
            t = time.monotonic()
            sync_rest(api, session, copy, frame="server")
            got.append((time.monotonic(), copy.have))
            time.sleep(max(0.0, 0.033 - (time.monotonic() - t)))
    api.close()
    out.put(got)


def live(mode: str, tmp: Path) -> dict:
    """The groove streamed at 1 kHz while another process keeps a copy by ``mode`` (``ws``
    or ``rest``)."""
    import multiprocessing as mp

    from ...client.demo import shortest_arc
    from ...client.rest import BurrRest
    from ...client.trajectory import Waypoint, stream
    from ...client.udp import BurrClient

    a = math.radians(60.0)
    q = shortest_arc((0.0, 0.0, 1.0), (-math.cos(a), 0.0, math.sin(a)))
    waypoints = [Waypoint((3.0 + 0.005 * i, 0.0, 1.5), q, 60_000.0) for i in range(3000)]
    tmp = tmp / mode
    tmp.mkdir()
    serve = spawn_serve(tmp, "--bone", "phantom:workpiece", "--token", TOKEN)
    url = serve.connection.http_url
    udp = (serve.connection.host, serve.connection.udp_port)
    try:
        api = BurrRest(url, TOKEN)
        s = api.create_session("phantom:workpiece", voxel_mm=0.1)
        ctx = mp.get_context("spawn")
        stop, out = ctx.Event(), ctx.Queue()
        follower = ctx.Process(target=_follow, args=(mode, url, s["id"], stop, out))
        follower.start()
        time.sleep(3.0)  # its initial copy
        announced: dict[int, float] = {}
        with BurrClient(udp[0], udp[1], s["id"], s["key"], timeout_s=1.0) as client:
            result = stream(client, waypoints, 1000.0)
        for r in result.results:
            if r is not None and r.reply.bone_version not in announced:
                # Arrival on the client's clock (now_us: monotonic), as the copy's times.
                announced[r.reply.bone_version] = (r.reply.t_client_us + r.rtt_us) / 1e6
        time.sleep(2.0)  # let the copy catch up
        stop.set()
        if mode == "ws":  # one more change wakes the push channel so it sees the stop
            with BurrClient(udp[0], udp[1], s["id"], s["key"], timeout_s=1.0) as client:
                for i in range(50):
                    client.exchange((20.0 + 0.01 * i, 0.0, 1.5), q, 60_000.0)
        got = out.get(timeout=30)
        follower.join(10)
        api.close()
    finally:
        serve.stop()
    times = np.array([g[0] for g in got])
    versions = np.array([g[1] for g in got])
    last = max(announced)
    lat = []
    for v, t_reply in announced.items():
        ok = np.nonzero((versions >= v) & (times >= t_reply))[0]
        if len(ok):
            lat.append(times[ok[0]] - t_reply)
    lat_ms = 1e3 * np.array(lat)
    return {"mode": mode, "versions": len(announced), "lost": result.lost,
            "late_sends": result.late_sends, "copies": len(got),
            "latency_ms_p50": float(np.median(lat_ms)), "latency_ms_p95":
            float(np.percentile(lat_ms, 95)), "latency_ms_max": float(lat_ms.max()),
            "caught_up": bool(versions.max() >= last)}


def run(progress=print, live_runs: bool = True) -> dict:
    rows = []
    for bone, voxel in BONES:
        for cb in CHUNK_BRICKS:
            progress(f"offline: {bone} at {voxel:g} mm, chunk_bricks {cb}")
            rows.append(offline(bone, voxel, cb))
    runs = []
    if live_runs:
        with tempfile.TemporaryDirectory(prefix="bench-mesh-") as tmp:
            for mode in ("ws", "rest"):
                progress(f"live: groove at 1 kHz, copy by {mode}")
                runs.append(live(mode, Path(tmp)))
    return {"offline": rows, "live": runs, "update_ticks": UPDATE_TICKS}


def write_results(result: dict, out: Path) -> tuple[Path, Path]:
    result, js = runner.save_json(out, "mesh", result)
    stamp = result["date"]
    lines = [
        "# Mesh chunks (`burrforce bench mesh`)", "",
        f"{stamp}; {result['machine']}. One run.", "",
        "Whole surface, and updates every 33 ticks (the WebSocket's default 33 ms) during a "
        "6 mm groove at 5 mm/s, 60 000 rpm, 0.5 mm deep, α = 60° (Unity frame; times are the "
        "server's meshing, in this process). Datagrams: 1472-byte UDP payloads an update "
        "would need as a side stream.", "",
        "| bone | voxel mm | chunk_bricks | chunk mm | chunks | triangles | full MB | full ms "
        "| updates | update kB p50 | max | chunks p50 | update ms p50 | max | datagrams p50 |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["offline"]:
        lines.append(
            f"| {r['bone']} | {r['voxel_mm']:g} | {r['chunk_bricks']} | {r['chunk_mm']:g} | "
            f"{r['full_chunks']} | {r['full_triangles']} | {r['full_bytes'] / 1e6:.2f} | "
            f"{r['full_ms']:.0f} | {r['updates']} | {r['update_bytes_p50'] / 1e3:.1f} | "
            f"{r['update_bytes_max'] / 1e3:.1f} | {r['update_chunks_p50']:.0f} | "
            f"{r['update_ms_p50']:.1f} | {r['update_ms_max']:.1f} | "
            f"{r['update_datagrams_p50']:.0f} |")
    if result["live"]:
        lines += ["", "Live: the Python client streams a 15 mm groove at 1 kHz into "
                  "`burrforce serve` (workpiece, 0.1 mm) while another process keeps a copy "
                  "(default chunk size); latency from a REPLY announcing a bone version "
                  "arriving to the copy holding it.", "",
                  "| channel | versions | lost | late sends | copies | latency ms p50 | p95 "
                  "| max | caught up |", "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
        for r in result["live"]:
            lines.append(f"| {r['mode']} | {r['versions']} | {r['lost']} | {r['late_sends']} "
                         f"| {r['copies']} | {r['latency_ms_p50']:.0f} | "
                         f"{r['latency_ms_p95']:.0f} | {r['latency_ms_max']:.0f} | "
                         f"{'yes' if r['caught_up'] else 'NO'} |")
    return runner.write_page(out, "mesh", lines), js


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "mesh", main, help="mesh chunks: sizes, meshing time, WebSocket vs REST latency",
        description="Chunk meshes of the phantoms per chunk size, updates during a groove, "
                    "and how fast an engine's copy follows over the WebSocket and over REST "
                    "polling. Writes OUT/mesh.md and mesh.json.")
    p.add_argument("--no-live", action="store_true", help="skip the live server runs")


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    return runner.report(args, *write_results(run(runner.say, not args.no_live), out))
