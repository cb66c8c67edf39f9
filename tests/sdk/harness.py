"""The engine SDKs' tests against one live ``burrforce serve`` (a subprocess on 127.0.0.1, the
workpiece phantom), and what they are compared with. The fixtures are registered by
``conftest.py``; the test modules import the helpers from here (``from harness import …``).

The groove every SDK cuts is defined here once (:func:`groove_position_mm`; README of
``client/``): the same poses, stamped on the same 1 ms schedule, as the Python client's
reference cut, so the server sees the same inputs and the steady forces must agree within 1 %.
Each SDK's test program prints its results as one JSON object; :func:`check_groove` compares
them, :func:`check_mesh_obj` checks the chunked mesh an SDK kept against the server's export.
"""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from burrforce.client.rest import BurrRest
from burrforce.client.trajectory import Waypoint, stream
from burrforce.client.udp import BurrClient
from burrforce.proto import frames
from burrforce.proto.messages import STATUS_CUTTING
from burrforce.server.bench.serve_process import spawn_serve

#: The groove (server frame, mm; the workpiece's top face is z = 0, the burr's radius 2 mm):
#: 1000 ticks plunging 1 mm from 0.5 mm above the surface, then 1200 ticks feeding 6 mm along
#: +x at 5 mm/s, 0.5 mm deep, at 60 000 rpm, the tool tilted 60° back against the feed.
PLUNGE_TICKS = 1000
FEED_TICKS = 1200
TICKS = PLUNGE_TICKS + FEED_TICKS + 1
#: Ticks from here on, with STATUS_CUTTING, are the steady part averaged.
STEADY_FROM = PLUNGE_TICKS + 240
RPM = 60_000.0
ANGLE_DEG = 60.0
#: Steady forces must agree with the Python client's this closely (relative).
FORCE_REL = 0.01


def groove_position_mm(i: int) -> tuple[float, float, float]:
    """Tick ``i``'s burr centre, server frame, mm (every SDK computes exactly this)."""
    if i <= PLUNGE_TICKS:
        return (3.0, 0.0, 2.5 - 0.001 * i)
    return (3.0 + 0.005 * (i - PLUNGE_TICKS), 0.0, 1.5)


def groove_axis() -> tuple[float, float, float]:
    """The tool axis toward the handle, server frame."""
    a = math.radians(ANGLE_DEG)
    return (-math.cos(a), 0.0, math.sin(a))


@pytest.fixture(scope="session")
def live_server(tmp_path_factory):
    """A running ``burrforce serve`` on the workpiece: a dict with ``host``, ``udp_port``,
    ``session`` (its own session 1), ``key_hex``, ``frame``, ``http_url`` (no ``/v1``),
    ``token`` and ``connection_file``. Stopped with SIGTERM at the end of the test run."""
    serve = spawn_serve(tmp_path_factory.mktemp("sdk-serve"), "--bone", "phantom:workpiece")
    c = serve.connection
    try:
        yield {"host": c.host, "udp_port": c.udp_port, "session": c.session,
               "key_hex": c.key_hex, "frame": c.frame, "http_url": c.http_url,
               "token": c.token, "connection_file": str(serve.connection_file)}
    finally:
        serve.stop()


@pytest.fixture(scope="session")
def rest(live_server):
    """The Python REST client of the live server."""
    with BurrRest(live_server["http_url"], live_server["token"]) as api:
        yield api


def new_session(rest: BurrRest, frame: str = "si_mm") -> dict:
    """A fresh session on its own workpiece (created over REST): ``id``, ``key``, ``udp``."""
    return rest.create_session("phantom:workpiece", parameters={"frame": frame})


def groove_waypoints(frame_name: str) -> list[Waypoint]:
    """The groove as engine-frame waypoints for a session in ``frame_name``."""
    frame = frames.frame(frame_name)
    tf = frames.Transform(frame)
    from burrforce.client.demo import shortest_arc
    q = shortest_arc(frame.tool_axis, tf.direction_out(groove_axis()))
    return [Waypoint(tf.point_out(groove_position_mm(i)), q, RPM, True) for i in range(TICKS)]


def summarize(status: np.ndarray, resistive: np.ndarray, force: np.ndarray,
              ticks: np.ndarray, rtt_us: np.ndarray, removed_mm3: float,
              sent: int) -> dict:
    """The groove's result in the JSON form every SDK's program prints: per reply (in tick
    order) its status, resistive (n, 3), force (n, 3, engine axes), tick index and round
    trip."""
    steady = (ticks >= STEADY_FROM) & ((status & STATUS_CUTTING) > 0)
    mean = resistive[steady].mean(axis=0) if steady.any() else np.zeros(3)
    return {
        "ticks": sent, "replies": len(ticks), "lost": sent - len(ticks),
        "steady_ticks": int(steady.sum()),
        "steady_feed_N": float(mean[0]), "steady_lateral_N": float(mean[1]),
        "steady_normal_N": float(mean[2]),
        "steady_force_N": float(np.linalg.norm(force[steady], axis=1).mean())
        if steady.any() else 0.0,
        "removed_mm3": float(removed_mm3),
        "rtt_p50_us": float(np.median(rtt_us)), "rtt_p99_us": float(np.percentile(rtt_us, 99)),
    }


@pytest.fixture(scope="session")
def python_groove(rest, live_server) -> dict:
    """The reference: the Python client cuts the groove in a fresh si_mm session."""
    s = new_session(rest)
    try:
        with BurrClient(live_server["host"], s["udp"]["port"], s["id"], s["key"],
                        timeout_s=1.0) as client:
            out = stream(client, groove_waypoints("si_mm"), 1000.0)
        got = [(i, r) for i, r in enumerate(out.results) if r is not None]
        ticks = np.array([i for i, _ in got])
        reps = [r.reply for _, r in got]
        result = summarize(np.array([r.status for r in reps], dtype=np.int64),
                           np.array([r.resistive for r in reps]).reshape(-1, 3),
                           np.array([r.force for r in reps]).reshape(-1, 3), ticks,
                           np.array([r.rtt_us for _, r in got]),
                           sum(r.removed_mm3 for r in reps), TICKS)
    finally:
        rest.delete_session(s["id"])
    assert result["steady_ticks"] > 500, result
    assert result["steady_feed_N"] < 0 < result["steady_normal_N"], result
    return result


def run_json(args: list[str], timeout_s: float = 180.0, **kwargs) -> dict:
    """Run an SDK's test program; its last stdout line is a JSON object."""
    p = subprocess.run(args, capture_output=True, text=True, timeout=timeout_s, **kwargs)
    assert p.returncode == 0, f"{args[0]} failed ({p.returncode}):\n{p.stdout}\n{p.stderr}"
    lines = [x for x in p.stdout.splitlines() if x.strip()]
    assert lines, f"{args[0]} printed nothing:\n{p.stderr}"
    return json.loads(lines[-1])


def check_groove(got: dict, reference: dict, max_lost: int = 20) -> None:
    """An SDK's groove against the Python client's: the same cut, steady forces within 1 %."""
    assert got["ticks"] == TICKS, got
    # Packets lost on the way: of those sent. A tick the client skipped because it woke late
    # (a busy machine: another process took the core) is no packet lost, and is bounded apart.
    lost = got["sent"] - got["replies"] if "sent" in got else got["lost"]
    assert lost <= max_lost, got
    assert got.get("skipped_ticks", 0) <= 0.05 * TICKS, got
    assert got["steady_ticks"] >= 0.9 * reference["steady_ticks"], (got, reference)
    for name in ("steady_feed_N", "steady_lateral_N", "steady_normal_N", "steady_force_N"):
        scale = max(abs(reference[name]), 0.01 * abs(reference["steady_force_N"]))
        assert abs(got[name] - reference[name]) <= FORCE_REL * scale, (name, got, reference)
    assert got["removed_mm3"] == pytest.approx(reference["removed_mm3"], rel=0.02)


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and 0-based triangles (m, 3) of an OBJ with ``v`` and ``f``
    lines (``f a b c``, or ``a//n`` forms)."""
    verts, faces = [], []
    for line in Path(path).read_text().splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "v":
            verts.append([float(x) for x in parts[1:4]])
        elif parts[0] == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in parts[1:4]])
    return (np.array(verts, dtype=np.float64).reshape(-1, 3),
            np.array(faces, dtype=np.int64).reshape(-1, 3))


def read_stl(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """A binary STL → vertices (3m, 3) float64 and triangles (m, 3)."""
    count = int(np.frombuffer(data, dtype="<u4", count=1, offset=80)[0])
    facet = np.dtype([("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec = np.frombuffer(data, dtype=facet, count=count, offset=84)
    return rec["v"].reshape(-1, 3).astype(np.float64), np.arange(3 * count).reshape(-1, 3)


def signed_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    v = verts - verts.mean(axis=0)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def weld(verts: np.ndarray, faces: np.ndarray, tol: float) -> np.ndarray:
    """Faces re-indexed onto vertices merged within ``tol`` (quantized positions)."""
    key = np.round(verts / tol).astype(np.int64)
    _, inverse = np.unique(key, axis=0, return_inverse=True)
    return inverse.reshape(-1)[faces]


def watertight(faces: np.ndarray) -> bool:
    """Every directed edge once and its reverse once: closed, consistently oriented."""
    f = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
              & (faces[:, 0] != faces[:, 2])]
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    directed, counts = np.unique(edges, axis=0, return_counts=True)
    if (counts != 1).any():
        return False
    reverse = np.unique(edges[:, ::-1], axis=0)
    return len(reverse) == len(directed) and bool((reverse == directed).all())


def check_mesh_obj(obj: Path, rest: BurrRest, session: int, frame_name: str,
                   winding: str) -> dict:
    """The union of an SDK's chunks (an OBJ in the session's frame and unit, as received)
    against the server's full export of the same bone: closed and consistently oriented
    after welding, and the same volume within 0.5 %."""
    verts, faces = read_obj(obj)
    assert len(faces), f"{obj} has no triangles"
    frame = frames.frame(frame_name)
    tf = frames.Transform(frame)
    server = np.array([tf.point_in(tuple(v)) for v in verts])  # mm, server frame
    if winding == "cw":  # numbers as delivered: reverse to the right-handed outward winding
        faces = faces[:, ::-1]
    if not frame.right_handed:  # a reflection flips it back
        faces = faces[:, ::-1]
    welded = weld(server, faces, 1e-4)
    stl = rest.export_mesh(session, Path(obj).with_suffix(".export.stl"), format="stl")
    ref_v, ref_f = read_stl(stl.read_bytes())
    volume, reference = signed_volume(server, faces), signed_volume(ref_v, ref_f)
    assert watertight(welded), "the chunks' union is not closed and consistently oriented"
    assert volume == pytest.approx(reference, rel=0.005), (volume, reference)
    return {"volume_mm3": volume, "export_volume_mm3": reference, "triangles": len(faces),
            "export_triangles": len(ref_f)}
