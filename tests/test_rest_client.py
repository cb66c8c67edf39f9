"""BurrRest against a live server: the hot loop in its own process, the control plane and
uvicorn in this one, everything on 127.0.0.1. A groove is cut over UDP with BurrClient, then
read back over REST (exports, deltas, snapshots, recordings). Every loop is bounded.

``live_server`` is shared with test_api_schema.py (tests/conftest.py belongs to the model
tests)."""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from burrforce.client import BurrClient
from burrforce.client.rest import BurrRest, RestError
from burrforce.proto.messages import STATUS_CUTTING

VOXEL_MM = 0.25
#: The workpiece's top face is z = 0; the burr's radius is 2 mm: a centre at z = 1.5 cuts
#: 0.5 mm deep.
CUT_Z_MM = 1.5
START_TIMEOUT_S = 120.0  # a cold numba cache compiles the kernels at the hot loop's start
LOAD_TIMEOUT_S = 60.0


@dataclass
class LiveServer:
    url: str
    token: str
    plane: object  # ControlPlane
    session_id: int  # the fixture session on phantom:workpiece, VOXEL_MM
    key_hex: str  # its key
    udp: tuple[str, int]  # the hot loop's address
    library: Path
    data_dir: Path

    def recreate_session(self) -> None:
        """The fixture session again as it started (same id and key, fresh settings and
        bone), whatever was done to it."""
        from burrforce.server.api.errors import ApiError

        _create_fixture_session(self.plane, self.session_id, self.key_hex, replace=True)
        try:
            self.plane.ready(self.session_id)
        except ApiError as exc:
            raise AssertionError(exc.detail) from None


def _create_fixture_session(plane, session_id: int | None = None, key_hex: str | None = None,
                            replace: bool = False):
    """A session on phantom:workpiece at VOXEL_MM with default settings, loaded."""
    from burrforce.server.api.errors import ApiError
    from burrforce.server.api.models import Features, Parameters

    if replace:
        try:
            plane.delete_session(session_id)
        except ApiError:
            pass  # already gone
    source = plane.resolve("phantom:workpiece", None, VOXEL_MM)
    session, job = plane.create_session(session_id, source, Parameters(), Features(),
                                        key_hex=key_hex)
    deadline = time.monotonic() + LOAD_TIMEOUT_S
    while plane.jobs[job.id].state in ("queued", "running"):
        assert time.monotonic() < deadline, "the fixture bone did not load in time"
        time.sleep(0.02)
    assert session.state == "ready", session.error
    return session


@contextlib.contextmanager
def live_server(tmp: Path) -> Iterator[LiveServer]:
    """What ``burrforce serve`` wires (hot loop → ControlPlane → session → LoopStats →
    uvicorn), on free loopback ports, with a bone library holding one small ``.bone.npz`` and
    a session on phantom:workpiece at VOXEL_MM."""
    import uvicorn

    from burrforce.server.api.app import create_app
    from burrforce.server.api.config import ServeConfig
    from burrforce.server.api.metrics import LoopStats
    from burrforce.server.api.plane import ControlPlane
    from burrforce.server.api.workers import start_hot_loop
    from burrforce.server.bone import phantom, save_bone

    library = tmp / "library"
    library.mkdir()
    save_bone(phantom("workpiece", VOXEL_MM), library / "block.bone.npz")
    token = secrets.token_urlsafe(24)
    config = ServeConfig(host="127.0.0.1", http_port=0, udp_port=0, token=token,
                         data_dir=tmp / "data", bone_library=library, upload_max_mb=4.0)
    hot = start_hot_loop(config)
    plane = stats = server = thread = None
    try:
        plane = ControlPlane(config, hot)
        session = _create_fixture_session(plane)
        stats = LoopStats(lambda since: hot.call("stats", tick_times_since=since))
        stats.poll()
        stats.start()
        app = create_app(plane, token, stats)
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0,
                                               log_level="warning", access_log=False))
        server.install_signal_handlers = lambda: None  # not the main thread
        thread = threading.Thread(target=server.run, name="test-uvicorn", daemon=True)
        thread.start()
        deadline = time.monotonic() + START_TIMEOUT_S
        while not server.started:
            assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.01)
        port = server.servers[0].sockets[0].getsockname()[1]
        yield LiveServer(f"http://127.0.0.1:{port}", token, plane, session.id,
                         session.key_hex, hot.address, library, tmp / "data")
    finally:
        if server is not None:
            server.should_exit = True
        if thread is not None:
            thread.join(10.0)
        if stats is not None:
            stats.stop()
        if plane is not None:
            plane.close()
        hot.stop()


@pytest.fixture(scope="module")
def live(tmp_path_factory) -> Iterator[LiveServer]:
    with live_server(tmp_path_factory.mktemp("rest-client")) as server:
        yield server


@pytest.fixture(scope="module")
def api(live) -> Iterator[BurrRest]:
    with BurrRest(live.url, live.token, timeout_s=30.0, load_timeout_s=LOAD_TIMEOUT_S) as c:
        yield c


@pytest.fixture(scope="module")
def cut(api):
    """A session of its own on the workpiece with a groove cut into it: (session, the
    remaining volume exported before the cut, the last UDP reply)."""
    s = api.create_session("phantom:workpiece", voxel_mm=VOXEL_MM)
    assert s["state"] == "ready" and s["key"]
    before = api.session(s["id"])
    assert before["bone"]["voxel_mm"] == pytest.approx(VOXEL_MM)
    host, port = s["udp"]["host"], s["udp"]["port"]
    results = []
    with BurrClient(host, port, session=s["id"], key=s["key"], timeout_s=2.0) as c:
        c.exchange((5.0, -4.0, 30.0), rpm=60_000)  # above the bone: a stream starts
        period_s = 1e-3
        deadline = time.monotonic() + 20.0
        next_t = time.monotonic()
        for k in range(600):  # 1.8 mm along x at 3 mm/s, ~1 kHz
            assert time.monotonic() < deadline, "the groove took too long"
            results.append(c.exchange((5.0 + 0.003 * k, -4.0, CUT_Z_MM), rpm=60_000))
            next_t += period_s
            pause = next_t - time.monotonic()
            if pause > 0:
                time.sleep(pause)
    assert results[-1].reply.status & STATUS_CUTTING
    assert results[-1].reply.removed_mm3 > 0.0
    return s, results[-1]


def test_health_metrics_and_phantoms(api, live):
    h = api.health()
    assert h["status"] == "ok" and h["hot_loop"] is True and h["sessions"] >= 1
    assert "burrforce_packets" in api.metrics_text()
    sources = {p["source"] for p in api.phantoms()}
    assert "phantom:workpiece" in sources
    assert [e["source"] for e in api.library()] == ["library:block.bone.npz"]
    assert any(s["id"] == live.session_id for s in api.sessions())
    assert api.session(live.session_id)["state"] == "ready"


def test_connection_file(tmp_path, live):
    from burrforce.client import connection

    path = connection.write(connection.Connection("127.0.0.1", 1, live.session_id, None,
                                                  "si_mm", VOXEL_MM, live.url + "/", live.token),
                            tmp_path / "connection.json")
    with BurrRest.from_connection(path) as c:
        assert c.url == live.url
        assert c.session(live.session_id)["id"] == live.session_id
    connection.write(connection.Connection("127.0.0.1", 1, 1, None, "si_mm"), path)
    with pytest.raises(ValueError, match="REST"):
        BurrRest.from_connection(path)


def test_wrong_token_and_unreachable_server(live):
    with BurrRest(live.url, "x" * 20) as c:
        with pytest.raises(RestError) as err:
            c.sessions()
        assert err.value.status == 401 and "token" in err.value.detail
        assert c.health()["status"] == "ok"  # needs no token
    with BurrRest("http://127.0.0.1:9", "x" * 20, timeout_s=2.0) as c:
        with pytest.raises(RestError) as err:
            c.health()
        assert err.value.status == 0 and "127.0.0.1:9" in err.value.detail


def test_export_volume_shows_the_groove(api, cut, tmp_path):
    from burrforce.server.bone import LoadOptions, load_bone

    s, last = cut
    untouched = api.export_volume(s["id"], tmp_path / "untouched.nrrd", what="density")
    carved = api.export_volume(s["id"], tmp_path / "carved.nrrd")
    assert not list(tmp_path.glob("*.part"))
    a = load_bone(untouched, LoadOptions(kind="density")).grid
    b = load_bone(carved, LoadOptions(kind="density")).grid
    assert a.shape == b.shape
    assert np.allclose(b.spacing_mm, VOXEL_MM)
    bone_a = float(np.sum(a.density, dtype=np.float64)) / 255.0
    bone_b = float(np.sum(b.density, dtype=np.float64)) / 255.0
    assert bone_b < bone_a
    # What the volume lost is what the loop says it removed (to the uint8 rounding).
    lost_mm3 = (bone_a - bone_b) * VOXEL_MM ** 3
    removed_mm3 = sum(api.state(s["id"])["removed_mm3"].values())
    assert lost_mm3 == pytest.approx(removed_mm3, rel=0.05)
    assert last.reply.bone_version == api.state(s["id"])["bone_version"]
    npy = api.export_volume(s["id"], tmp_path / "labels.npy", format="npy", what="labels")
    assert np.load(npy).shape == tuple(a.shape)


def test_export_mesh_is_a_binary_stl(api, cut, tmp_path):
    s, _ = cut
    path = api.export_mesh(s["id"], tmp_path / "bone.stl", step=2)
    data = path.read_bytes()
    triangles = int.from_bytes(data[80:84], "little")
    assert triangles > 100 and len(data) == 84 + 50 * triangles
    xyz = np.frombuffer(data[84:], dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)),
                                                   ("a", "<u2")]))["v"].reshape(-1, 3)
    # The workpiece spans 26 × 16 × 8 mm with its top face at z = 0.
    assert -9.0 < xyz[:, 2].min() < -7.0 and -0.5 < xyz[:, 2].max() < 0.5


def test_deltas_since_zero(api, cut):
    s, _ = cut
    d = api.deltas(s["id"], since=0)
    assert d["format"] == "burrforce-bricks" and d["count"] > 0
    assert d["bricks"].shape == (d["count"], 3) and d["bricks"].dtype == np.int32
    assert d["remaining"].shape == (d["count"], 8, 8, 8) and d["remaining"].dtype == np.uint8
    assert d["complete"] and d["next_since"] == d["bone_version"] > 0
    # Bricks around the groove: x 5–7 mm, y −4 mm, near the top face.
    assert d["remaining"].min() < 255
    again = api.deltas(s["id"], since=d["next_since"])
    assert again["count"] == 0 and again["complete"]
    paged = api.deltas(s["id"], since=0, max_bricks=1)
    assert paged["count"] <= 1


def test_snapshot_and_restore_round_trip(api, cut, tmp_path):
    s, _ = cut
    version = api.state(s["id"])["bone_version"]
    carved = _volume(api, s["id"], tmp_path / "carved.npy")
    snap = api.snapshot(s["id"], name="groove")
    assert snap["source"] == "snapshot:groove" and snap["bytes"] > 0
    assert "groove" in {x["name"] for x in api.snapshots()}
    with pytest.raises(RestError) as err:
        api.snapshot(s["id"], name="groove")
    assert err.value.status == 409 and "groove" in err.value.detail
    api.download_snapshot("groove", tmp_path / "groove.bone.npz")
    with pytest.raises(RestError) as err:  # a name the route's pattern passes, but not ours
        api.download_snapshot("AJkd..-1e0ZRU", tmp_path / "bad.bone.npz")
    assert err.value.status == 400 and "letters, digits" in err.value.detail
    assert (tmp_path / "groove.bone.npz").stat().st_size == snap["bytes"]
    job = api.reset(s["id"])
    assert job["state"] == "done" and job["kind"] == "reset", job
    assert api.state(s["id"])["bone_version"] == 0
    assert api.deltas(s["id"], since=0)["count"] == 0
    uncarved = _volume(api, s["id"], tmp_path / "reset.npy")
    assert int(uncarved.sum()) > int(carved.sum())
    job = api.restore(s["id"], snap["source"])
    assert job["state"] == "done" and job["kind"] == "restore", job
    assert api.state(s["id"])["bone_version"] == version
    assert api.session(s["id"])["source"] == "snapshot:groove"
    assert np.array_equal(_volume(api, s["id"], tmp_path / "restored.npy"), carved)


def test_deltas_since_zero_cover_a_restored_carving(api, cut, tmp_path):
    s, _ = cut
    names = {x["name"] for x in api.snapshots()}
    if "groove" not in names:
        api.snapshot(s["id"], name="groove")
    assert api.restore(s["id"], "groove")["state"] == "done"
    d = api.deltas(s["id"], since=0)
    assert d["count"] > 0


def test_a_huge_tool_axis_is_refused_or_works(api):
    s = api.create_session("phantom:workpiece", voxel_mm=0.5)
    try:
        try:
            api.set_parameters(s["id"], tool_axis=[1e200, 0.0, 0.0])
        except RestError as err:
            assert err.status == 422 and "tool_axis" in err.detail
            return
        with BurrClient(s["udp"]["host"], s["udp"]["port"], session=s["id"], key=s["key"],
                        timeout_s=2.0) as c:
            assert c.exchange((5.0, -4.0, 30.0), rpm=60_000).reply.error == 0
    finally:
        api.delete_session(s["id"])


def test_recording_started_and_stopped(api, cut):
    s, _ = cut
    started = api.start_recording(s["id"], name="groove-rec")
    assert started["name"] == "groove-rec.burrrec"
    assert api.session(s["id"])["recording"] == "groove-rec.burrrec"
    assert api.recording(s["id"])["name"] == "groove-rec.burrrec"
    with BurrClient(s["udp"]["host"], s["udp"]["port"], session=s["id"], key=s["key"],
                    timeout_s=2.0) as c:
        for k in range(50):
            c.exchange((5.0 + 0.003 * k, 4.0, 30.0), rpm=60_000)
    stopped = api.stop_recording(s["id"])
    assert stopped["name"] == "groove-rec.burrrec"
    assert api.session(s["id"])["recording"] is None
    with pytest.raises(RestError) as err:
        api.recording(s["id"])
    assert err.value.status == 404
    recs = {r["name"]: r for r in api.recordings()}
    assert recs["groove-rec.burrrec"]["bytes"] > 0


def test_parameters_features_and_materials(api, cut):
    s, _ = cut
    p = api.set_parameters(s["id"], us_n_mm2=1610.0, k=0.5, tool_axis=np.array([0, 0, 1.0]))
    assert p["us_n_mm2"] == 1610.0 and p["k"] == 0.5 and p["tool_axis"] == [0.0, 0.0, 1.0]
    assert api.parameters(s["id"])["us_n_mm2"] == 1610.0
    with pytest.raises(RestError) as err:
        api.set_parameters(s["id"], radius_mm=-1.0)
    assert err.value.status == 422
    assert "radius_mm" in err.value.detail and "greater than" in err.value.detail
    assert err.value.errors and err.value.errors[0]["loc"][-1] == "radius_mm"
    with pytest.raises(RestError) as err:
        api.set_parameters(s["id"], radius=2.0)
    assert err.value.status == 422 and "radius" in err.value.detail
    assert api.parameters(s["id"])["radius_mm"] == p["radius_mm"]  # all or nothing
    f = api.set_features(s["id"], vibration=False)
    assert f["vibration"] is False and f["carving"] is True
    assert api.features(s["id"]) == f
    assert api.set_features(s["id"], vibration=True)["vibration"] is True
    table = {m["label"]: m for m in api.materials(s["id"])}
    assert table[1]["us_n_mm2"] == 1610.0
    m = api.set_material(s["id"], 1, k=0.6)
    assert m["k"] == 0.6 and m["us_n_mm2"] == 1610.0
    m = api.set_material(s["id"], 7, name="drape", us_n_mm2=10.0, k=0.1, forbidden=True,
                         replace=True)
    assert m == {"label": 7, "name": "drape", "us_n_mm2": 10.0, "k": 0.1, "forbidden": True}
    with pytest.raises(RestError) as err:
        api.set_material(s["id"], 99, k=0.1)
    assert err.value.status == 404


def test_upload_load_bone_jobs_and_delete(api, live, tmp_path):
    from burrforce.server.bone import phantom, save_bone

    path = tmp_path / "small.bone.npz"
    save_bone(phantom("workpiece", 0.5), path)
    source = api.upload(path)
    assert source.startswith("upload:")
    s = api.create_session("library:block.bone.npz", wait=False, authenticated=False)
    job = api.wait_for_job(s["job"], timeout_s=LOAD_TIMEOUT_S)
    assert job["state"] == "done", job
    assert api.session(s["id"])["authenticated"] is False
    job = api.load_bone(s["id"], source)
    assert job["state"] == "done", job
    assert api.session(s["id"])["bone"]["voxel_mm"] == pytest.approx(0.5)
    assert api.job(job["id"])["state"] == "done"
    api.restart_stream(s["id"])
    with pytest.raises(RestError) as err:
        api.load_bone(s["id"], "library:../etc/passwd", kind="density")
    assert err.value.status == 400 and "leaves the library" in err.value.detail
    with pytest.raises(RestError) as err:
        api.create_session("phantom:nope")
    assert err.value.status == 404 and "unknown phantom 'nope'" in err.value.detail
    empty = tmp_path / "empty.nrrd"
    empty.write_bytes(b"")
    with pytest.raises(RestError) as err:
        api.upload(empty)
    assert err.value.status == 422 and "empty" in err.value.detail
    api.delete_session(s["id"])
    with pytest.raises(RestError) as err:
        api.session(s["id"])
    assert err.value.status == 404


def _volume(api: BurrRest, session_id: int, path: Path) -> np.ndarray:
    """The session's remaining bone (uint8 0–255) through an npy export."""
    return np.load(api.export_volume(session_id, path, format="npy"))


def test_devices_attach_status_detach(api):
    assert {d["name"] for d in api.devices()} >= {"sim", "falcon", "audio", "wav"}
    s = api.create_session(bone="phantom:workpiece", voxel_mm=0.2)
    try:
        status = api.attach_device(s["id"], "sim:hand=groove,depth_mm=4", spindle="on")
        assert status["state"] in ("homing", "running")
        with pytest.raises(RestError) as busy:
            api.attach_device(s["id"], "sim")
        assert busy.value.status == 409
        assert api.device_status(s["id"])["device"] == "sim:hand=groove,depth_mm=4"
        assert api.parameters(s["id"])["device"] == "generic"  # coupled for the sim's profile
        detached = api.detach_device(s["id"])
        assert detached["state"] == "stopped", detached  # its events say why if not
        with pytest.raises(RestError) as gone:
            api.device_status(s["id"])
        assert gone.value.status == 404
        with pytest.raises(RestError) as bad:
            api.attach_device(s["id"], "sim:hand=zigzag")
        assert bad.value.status == 422 and "hand script" in bad.value.detail
    finally:
        api.delete_session(s["id"])
