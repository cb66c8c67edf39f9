"""The REST control plane against the real stack: a hot-loop process, uvicorn on 127.0.0.1,
httpx, real UDP clients cutting, real files. Every wait is bounded."""

from __future__ import annotations

import json
import math
import time

import httpx
import numpy as np
import pytest

from burrforce.client import BurrClient
from burrforce.proto.bricks import decode_delta
from burrforce.proto.messages import (
    STATUS_CLAMPED,
    STATUS_CUTTING,
    UNKNOWN_SESSION,
)
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack
from burrforce.server.bone import LoadOptions, load_bone, phantom, save_bone
from burrforce.server.record import replay

TOKEN = "test-token-0123456789abcdef"
VOXEL_MM = 0.25
FEED = (3.0, 0.0, 0.0)  # mm/s, sent with each pose so forces do not depend on timing


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    library = tmp_path_factory.mktemp("library")
    save_bone(phantom("workpiece", VOXEL_MM), library / "block.bone.npz")
    np.save(library / "raw.npy", np.full((40, 40, 20), 255, dtype=np.uint8))
    (library / "notes.txt").write_text("not a bone")
    config = ServeConfig(http_port=0, udp_port=0, data_dir=data, bone_library=library,
                         upload_max_mb=1.0)
    with ServerStack(config, TOKEN) as s:
        yield s


@pytest.fixture(scope="module")
def api(stack):
    with httpx.Client(base_url=stack.url + "/v1", timeout=120.0,
                      headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        yield client


def _session(api, **body) -> dict:
    body.setdefault("bone", {"source": "phantom:workpiece", "voxel_mm": VOXEL_MM})
    r = api.post("/sessions", json=body)
    assert r.status_code == 201, r.text
    return r.json()


def _groove(stack, s: dict, y_mm: float, ticks: int = 150, rpm: float = 60_000,
            z_mm: float = 1.5) -> list:
    """Feed along +x at y, 0.5 mm deep in the workpiece; the replies."""
    with BurrClient(*stack.udp_address, session=s["id"], key=s.get("key"),
                    timeout_s=2.0) as c:
        out = [c.exchange((2.0, y_mm, z_mm), rpm=rpm, velocity=FEED)]
        out += [c.exchange((2.0 + 0.003 * k, y_mm, z_mm), rpm=rpm, velocity=FEED)
                for k in range(1, ticks)]
    return [r.reply for r in out]


def _steady(replies) -> np.ndarray:
    forces = np.array([r.force for r in replies[-50:]])
    assert all(r.status & STATUS_CUTTING for r in replies[-50:])
    return forces.mean(axis=0)


# -- security ---------------------------------------------------------------------------------
def test_every_route_but_health_needs_the_token(stack):
    with httpx.Client(base_url=stack.url, timeout=30.0) as anon:
        assert anon.get("/v1/health").status_code == 200
        for path in ("/v1/sessions", "/v1/phantoms", "/metrics", "/v1/snapshots"):
            r = anon.get(path)
            assert r.status_code == 401 and "token" in r.json()["detail"]
            assert r.headers["www-authenticate"] == "Bearer"
        r = anon.get("/v1/sessions", headers={"Authorization": "Bearer wrong-token-xxxxxxxx"})
        assert r.status_code == 401
        # CORS is off: no allow-origin header for a browser's preflight.
        r = anon.options("/v1/sessions", headers={"Origin": "http://evil.example",
                                                  "Access-Control-Request-Method": "GET"})
        assert "access-control-allow-origin" not in r.headers


# -- sessions -----------------------------------------------------------------------------------
def test_create_list_get_delete(stack, api):
    s = _session(api, id=40)
    assert s["state"] == "ready" and len(s["key"]) == 64
    assert s["udp"]["port"] == stack.udp_address[1]
    assert s["bone"]["shape"] and s["bone"]["voxel_mm"] == VOXEL_MM
    assert api.post("/sessions", json={"id": 40}).status_code == 409
    assert any(x["id"] == 40 for x in api.get("/sessions").json())
    got = api.get("/sessions/40").json()
    assert "key" not in got and got["source"] == "phantom:workpiece"
    assert _groove(stack, s, 0.0, 30)[-1].status & STATUS_CUTTING
    assert api.delete("/sessions/40").status_code == 204
    assert api.get("/sessions/40").status_code == 404
    # The session is gone from the hot loop too: its datagrams get UNKNOWN_SESSION.
    with BurrClient(*stack.udp_address, session=40, key=s["key"], timeout_s=1.0) as c:
        with pytest.raises(Exception) as err:
            c.exchange((2.0, 0.0, 1.5), rpm=60_000)
    assert getattr(err.value, "code", None) == UNKNOWN_SESSION


@pytest.mark.parametrize(("bone", "status", "words"), [
    ({"source": "phantom:nope"}, 404, "unknown phantom"),
    ({"source": "library:../../etc/passwd", "kind": "ct"}, 400, "leaves the library"),
    ({"source": "library:/etc/passwd", "kind": "ct"}, 400, "relative"),
    ({"source": "library:missing.nrrd", "kind": "ct"}, 404, "no 'missing.nrrd'"),
    ({"source": "library:raw.npy"}, 422, "say which with kind"),
    ({"source": "library:notes.txt", "kind": "ct"}, 422, "unknown bone format"),
    ({"source": "upload:0123456789abcdef"}, 404, "no upload"),
    ({"source": "ftp:x"}, 422, "scheme"),
    ({"source": "phantom:workpiece", "voxel_mm": 5.0}, 422, "coarser than the burr"),
])
def test_bad_bones_are_refused_with_a_reason(api, bone, status, words):
    r = api.post("/sessions", json={"bone": bone})
    assert r.status_code == status, r.text
    assert words in json.dumps(r.json()["detail"])


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity"])
def test_a_voxel_size_that_is_not_a_number_is_named_so(api, value):
    """Python's JSON reads NaN and Infinity: they are refused as what they are, not as out of
    range."""
    r = api.post("/sessions", headers={"Content-Type": "application/json"},
                 content=f'{{"bone": {{"source": "phantom:workpiece", "voxel_mm": {value}}}}}')
    assert r.status_code == 422, r.text
    assert "finite number" in json.dumps(r.json()["detail"])


def test_library_bones_load_and_list(api):
    listing = {e["source"]: e for e in api.get("/library").json()}
    assert listing["library:block.bone.npz"]["needs_kind"] is False
    assert listing["library:raw.npy"]["needs_kind"] is True
    assert "library:notes.txt" not in listing
    s = _session(api, bone={"source": "library:raw.npy", "kind": "density",
                            "spacing_mm": [0.25, 0.25, 0.25]})
    assert s["bone"]["shape"] == [40, 40, 20]
    api.delete(f"/sessions/{s['id']}")


def test_upload_with_a_byte_budget(api, tmp_path):
    path = tmp_path / "cube.npy"
    np.save(path, np.full((30, 30, 30), 255, dtype=np.uint8))
    r = api.post("/uploads", params={"filename": "cube.npy"}, content=path.read_bytes())
    assert r.status_code == 201, r.text
    source = r.json()["source"]
    s = _session(api, bone={"source": source, "kind": "density",
                            "spacing_mm": [0.2, 0.2, 0.2]})
    assert s["bone"]["shape"] == [30, 30, 30]
    api.delete(f"/sessions/{s['id']}")
    big = b"\0" * (1 << 20) + b"x"
    r = api.post("/uploads", params={"filename": "big.npy"}, content=big)
    assert r.status_code == 413 and "limit" in r.json()["detail"]
    # Streamed without a length: the budget still holds.
    r = api.post("/uploads", params={"filename": "big.npy"},
                 content=iter([big[:600_000], big[600_000:]]))
    assert r.status_code == 413
    assert api.post("/uploads", params={"filename": "noext"}, content=b"x").status_code == 422
    assert api.post("/uploads", params={"filename": "e.npy"}, content=b"").status_code == 422


def test_a_long_load_is_a_job(api):
    r = api.post("/sessions", params={"wait": "false"},
                 json={"bone": {"source": "phantom:workpiece", "voxel_mm": 0.2}})
    assert r.status_code in (201, 202)
    s = r.json()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        job = api.get(f"/jobs/{s['job']}").json()
        if job["state"] in ("done", "failed"):
            break
        time.sleep(0.05)
    assert job["state"] == "done", job
    assert api.get(f"/sessions/{s['id']}").json()["state"] == "ready"
    assert api.get("/jobs/0000000000000000").status_code == 404
    api.delete(f"/sessions/{s['id']}")


# -- parameters -----------------------------------------------------------------------------
def test_doubling_us_doubles_the_force(stack, api):
    s = _session(api)
    sid = s["id"]
    base = _steady(_groove(stack, s, -4.0))
    p = api.get(f"/sessions/{sid}/parameters").json()
    assert p["us_n_mm2"] == pytest.approx(805.1) and p["primary_material_name"] == "cortical"
    r = api.patch(f"/sessions/{sid}/parameters", json={"us_n_mm2": 2 * 805.1})
    assert r.status_code == 200 and r.json()["us_n_mm2"] == pytest.approx(1610.2)
    doubled = _steady(_groove(stack, s, 4.0))
    np.testing.assert_allclose(doubled, 2.0 * base, rtol=0.02, atol=0.01)
    # K scales each element's normal force: with the tool axis vertical the tangential
    # (cutting-velocity) forces are horizontal, so the vertical component doubles with K.
    api.patch(f"/sessions/{sid}/parameters", json={"us_n_mm2": 805.1, "k": 2.6})
    k2 = _steady(_groove(stack, s, 0.0))
    assert k2[2] == pytest.approx(2.0 * base[2], rel=0.03)
    # A reset reloads the bone and keeps the user's Us/K.
    r = api.post(f"/sessions/{sid}/reset")
    assert r.status_code == 202 and r.json()["state"] == "done"
    assert api.get(f"/sessions/{sid}/parameters").json()["k"] == 2.6
    assert api.get(f"/sessions/{sid}/state").json()["bone_version"] == 0
    api.delete(f"/sessions/{sid}")


@pytest.mark.parametrize(("body", "words"), [
    ({"us_n_mm2": -1}, "greater than or equal"),
    ({"us_n_mm2": "NaN"}, "finite"),
    ({"radius_mm": 100}, "less than or equal to 5"),
    ({"radius_mm": 0.1}, "greater than or equal to 0.25"),
    ({"shaft_length_mm": 1000}, "less than or equal to 200"),
    ({"tool_axis": [1.7e308, 1.7e308, 1.7e308]}, "finite"),
    ({"placement_orientation": [1.7e308, 1.7e308, 1.7e308, 1.7e308]}, "finite"),
    ({"placement_position": [1e308, 0, 0]}, "less than or equal to 1000000000"),
    ({"radius_mm": 0.5}, "shaft radius 1.0 mm must be smaller"),
    ({"shaft_radius_mm": 3.0}, "shaft radius"),
    ({"frame": "blender"}, "si_mm"),
    ({"tool_axis": [0, 0, 0]}, "zero"),
    ({"primary_material": 9}, "no material with label 9"),
    ({"bogus": 1}, "extra"),
    ({"burr": {"shape": {"kind": "cone", "radius_mm": 1.0}}}, "kind must be one of"),
    ({"burr": {"shape": {"kind": []}}}, "kind must be one of"),
    ({"burr": {"shape": {"kind": "cylinder", "radius_mm": 1.0}}}, "missing ['length_mm']"),
    ({"burr": {"shape": {"kind": "sphere", "radius_mm": 2.0},
               "cutter": {"kind": "fluted", "n_flutes": 0}}}, "n_flutes"),
    ({"burr": {"shape": {"kind": "sphere", "radius_mm": 2.0}}, "radius_mm": 1.5},
     "disagrees with the burr's shape"),
    ({"burr": {"shape": {"kind": "sphere", "radius_mm": 9.0}}}, "largest radius must be in"),
    ({"burr": {"shape": {"kind": "cylinder", "radius_mm": 1.0, "length_mm": 50.0}}},
     "at most 20 mm long"),
])
def test_bad_parameters_change_nothing(api, body, words):
    before = api.get("/sessions/1/parameters")
    if before.status_code == 404:  # the module's first session is made here
        _session(api, id=1)
        before = api.get("/sessions/1/parameters")
    r = api.patch("/sessions/1/parameters", json=body)
    assert r.status_code == 422, r.text
    assert words in json.dumps(r.json()["detail"])
    assert api.get("/sessions/1/parameters").json() == before.json()


def test_frame_change_applies_to_the_stream(stack, api):
    s = _session(api)
    r = api.patch(f"/sessions/{s['id']}/parameters", json={"frame": "unreal"})
    assert r.json()["frame"] == "unreal"
    # Unreal: left-handed Z-up centimetres, x forward, y right. The workpiece's (2, -y, 1.5)
    # mm is (0.2, y/10, 0.15) cm with y flipped.
    with BurrClient(*stack.udp_address, session=s["id"], key=s["key"], timeout_s=2.0) as c:
        c.exchange((0.2, 0.0, 0.15), rpm=60_000, velocity=(0.3, 0, 0))
        reply = [c.exchange((0.2 + 0.0003 * k, 0.0, 0.15), rpm=60_000, velocity=(0.3, 0, 0))
                 for k in range(1, 60)][-1].reply
    assert reply.status & STATUS_CUTTING
    api.delete(f"/sessions/{s['id']}")


# -- features -------------------------------------------------------------------------------
def test_features_off_are_skipped(stack, api):
    s = _session(api)
    sid = s["id"]
    f = api.get(f"/sessions/{sid}/features").json()
    assert f == {"model": True, "carving": True, "vibration": True, "shaft": True,
                 "deltas": True, "coupling": None}
    assert api.get(f"/sessions/{sid}").json()["output"] == "raw"
    r = api.put(f"/sessions/{sid}/features", json={**f, "coupling": "sometimes"})
    assert r.status_code == 422
    api.put(f"/sessions/{sid}/features", json={**f, "carving": False, "vibration": False})
    replies = _groove(stack, s, 0.0, 60)
    assert replies[-1].status & STATUS_CUTTING and replies[-1].removed_mm3 == 0.0
    assert replies[-1].vibration_amplitude == 0.0
    assert api.get(f"/sessions/{sid}/state").json()["bone_version"] == 0
    api.put(f"/sessions/{sid}/features", json={**f, "model": False})
    assert _groove(stack, s, 0.0, 20)[-1].force == (0.0, 0.0, 0.0)
    api.put(f"/sessions/{sid}/features", json={**f, "deltas": False})
    r = api.get(f"/sessions/{sid}/export/volume")
    assert r.status_code == 409 and "deltas off" in r.json()["detail"]
    api.delete(f"/sessions/{sid}")


# -- materials and state ----------------------------------------------------------------------
def test_materials_and_forbidden_events(stack, api):
    s = _session(api)
    sid = s["id"]
    table = api.get(f"/sessions/{sid}/materials").json()
    assert table == [{"label": 1, "name": "cortical", "us_n_mm2": 805.1, "k": 1.3,
                      "forbidden": False}]
    r = api.patch(f"/sessions/{sid}/materials/1", json={"forbidden": True})
    assert r.status_code == 200 and r.json()["forbidden"] is True
    assert api.patch(f"/sessions/{sid}/materials/7", json={"k": 1}).status_code == 404
    r = api.put(f"/sessions/{sid}/materials/2", json={"name": "cortical", "us_n_mm2": 1,
                                                      "k": 1})
    assert r.status_code == 422 and "cortical" in r.text  # names are unique
    for bad in ("cort\x00ical", "two\nlines", "\x1b[31mred"):  # NUL, newline, escape
        r = api.put(f"/sessions/{sid}/materials/2", json={"name": bad, "us_n_mm2": 1, "k": 1})
        assert r.status_code == 422 and "control characters" in r.text, (bad, r.text)
        r = api.patch(f"/sessions/{sid}/materials/1", json={"name": bad})
        assert r.status_code == 422 and "control characters" in r.text, (bad, r.text)
    assert [m["name"] for m in api.get(f"/sessions/{sid}/materials").json()] == ["cortical"]
    _groove(stack, s, 0.0, 30)
    state = api.get(f"/sessions/{sid}/state").json()
    assert state["forbidden_events"] >= 1
    event = state["events"][0]
    assert event["material"] == "cortical" and len(event["position_mm"]) == 3
    assert state["removed_mm3"]["cortical"] > 0 and state["bone_version"] > 0
    # The loop's clock when it read the counters: the live view's packet rate is
    # Δaccepted / Δt_loop_s, not skewed by how long each request took.
    _groove(stack, s, 1.0, 30)
    later = api.get(f"/sessions/{sid}/state").json()
    assert later["t_loop_s"] > state["t_loop_s"] and later["accepted"] >= state["accepted"] + 30
    api.delete(f"/sessions/{sid}")


# -- exports, deltas, snapshots, recordings --------------------------------------------------
def test_exports_show_the_groove(stack, api, tmp_path):
    s = _session(api)
    sid = s["id"]
    _groove(stack, s, 0.0, 300)
    r = api.get(f"/sessions/{sid}/export/volume", params={"format": "nrrd"})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-nrrd"
    path = tmp_path / "carved.nrrd"
    path.write_bytes(r.content)
    carved = load_bone(path, LoadOptions(kind="density"))
    pristine = phantom("workpiece", VOXEL_MM)
    lost = sum(pristine.volumes_mm3().values()) - sum(carved.volumes_mm3().values())
    removed = api.get(f"/sessions/{sid}/state").json()["removed_mm3"]["cortical"]
    assert lost == pytest.approx(removed, rel=0.02) and lost > 1.0
    # The groove is where the burr went: bone missing at (3, 0, -0.2), intact at (3, 5, -0.2).
    grid = carved.grid

    def at(x, y, z):
        index = np.rint(grid.to_grid_point((x, y, z)) / grid.spacing_mm).astype(int)
        return int(grid.density[tuple(index)])
    assert at(3.0, 0.0, -0.2) == 0 and at(3.0, 5.0, -0.2) == 255
    npy = api.get(f"/sessions/{sid}/export/volume", params={"format": "npy",
                                                             "what": "labels"})
    (tmp_path / "l.npy").write_bytes(npy.content)
    assert np.load(tmp_path / "l.npy").shape == tuple(s["bone"]["shape"])
    for fmt, magic in (("stl", None), ("ply", b"ply"), ("obj", b"# burrforce")):
        m = api.get(f"/sessions/{sid}/export/mesh", params={"format": fmt, "step": 2})
        assert m.status_code == 200 and len(m.content) > 1000
        if magic:
            assert m.content.startswith(magic)
    assert api.get(f"/sessions/{sid}/export/mesh", params={"level": 1.5}).status_code == 422
    d = decode_delta(api.get(f"/sessions/{sid}/deltas", params={"since": 0}).content)
    assert d["count"] > 0 and d["bone_version"] > 0 and d["complete"]
    r = api.get(f"/sessions/{sid}/deltas", params={"since": 10**9})
    assert r.status_code == 422 and "newer than the bone" in r.text
    api.delete(f"/sessions/{sid}")


def test_snapshot_and_restore(stack, api):
    s = _session(api)
    sid = s["id"]
    _groove(stack, s, 0.0, 100)
    version = api.get(f"/sessions/{sid}/state").json()["bone_version"]
    snap = api.post(f"/sessions/{sid}/snapshot", json={"name": f"groove-{sid}"}).json()
    assert snap["source"] == f"snapshot:groove-{sid}"
    assert api.post(f"/sessions/{sid}/snapshot",
                    json={"name": f"groove-{sid}"}).status_code == 409
    assert any(x["name"] == f"groove-{sid}" for x in api.get("/snapshots").json())
    api.post(f"/sessions/{sid}/reset")
    assert api.get(f"/sessions/{sid}/state").json()["bone_version"] == 0
    r = api.post(f"/sessions/{sid}/restore", json={"snapshot": f"groove-{sid}"})
    assert r.json()["state"] == "done"
    state = api.get(f"/sessions/{sid}/state").json()
    assert state["bone_version"] == version
    # A new session can start from it too.
    t = _session(api, bone={"source": f"snapshot:groove-{sid}"})
    assert t["state"] == "ready"
    assert api.post(f"/sessions/{sid}/restore",
                    json={"snapshot": "../etc"}).status_code == 422
    assert api.get(f"/snapshots/groove-{sid}").content[:2] == b"PK"
    api.delete(f"/sessions/{sid}")
    api.delete(f"/sessions/{t['id']}")


def test_recording_replays_exactly(stack, api):
    s = _session(api)
    sid = s["id"]
    _groove(stack, s, -3.0, 50)  # carved before the recording: in its start snapshot
    r = api.post(f"/sessions/{sid}/recording", json={"name": f"rec-{sid}"})
    assert r.status_code == 201, r.text
    assert api.post(f"/sessions/{sid}/recording").status_code == 409
    replies = _groove(stack, s, 3.0, 200)
    status = api.get(f"/sessions/{sid}/recording").json()
    assert status["rows"] >= 200
    stopped = api.delete(f"/sessions/{sid}/recording").json()
    assert stopped["name"] == f"rec-{sid}.burrrec"
    listing = {x["name"]: x for x in api.get("/recordings").json()}
    assert listing[f"rec-{sid}.burrrec"]["complete"]
    report = replay(stack.plane.recordings_dir / f"rec-{sid}.burrrec")
    assert report.reproduced and report.ticks == status["rows"]
    assert report.removed_mm3 == pytest.approx(sum(r.removed_mm3 for r in replies), rel=1e-6)
    api.delete(f"/sessions/{sid}")


def test_metrics(stack, api):
    s = _session(api)
    _groove(stack, s, 0.0, 100)
    time.sleep(1.2)  # two polls of the statistics
    text = httpx.get(stack.url + "/metrics",
                     headers={"Authorization": f"Bearer {TOKEN}"}).text
    assert 'burrforce_packets_total{outcome="received"}' in text
    assert 'outcome="wake_' not in text  # the loop's polling is not a datagram outcome
    for event in ("caught", "missed", "starved", "busy", "quiet", "preempted", "early",
                  "irregular"):
        assert f'burrforce_wake_ahead_total{{event="{event}"}}' in text
    assert "burrforce_wake_poll_seconds_total" in text
    assert f'burrforce_tick_seconds_bucket{{le="+Inf",session="{s["id"]}"}}' in text
    count = [line for line in text.splitlines()
             if line.startswith(f'burrforce_tick_seconds_count{{session="{s["id"]}"}}')]
    assert count and float(count[0].split()[-1]) >= 100
    assert "burrforce_removed_mm3" in text
    api.delete(f"/sessions/{s['id']}")


def test_engine_changes_keep_the_stream_and_a_frame_change_restarts_it(stack, api):
    from burrforce.proto.messages import STATUS_STALE

    s = _session(api)
    sid = s["id"]
    with BurrClient(*stack.udp_address, session=sid, key=s["key"], timeout_s=2.0) as c:
        for k in range(20):  # velocity from the client's stamps: a restart makes it stale
            c.exchange((2.0 + 0.003 * k, 0.0, 1.5), rpm=60_000)
            time.sleep(0.001)
        for body in ({"us_n_mm2": 900.0}, {"fd_N": 0.2}, {"min_cutting_rpm": 4000}):
            assert api.patch(f"/sessions/{sid}/parameters", json=body).status_code == 200
            r = c.exchange((2.1, 0.0, 1.5), rpm=60_000).reply
            assert not r.status & STATUS_STALE, body
        api.patch(f"/sessions/{sid}/materials/1", json={"forbidden": True})
        assert not c.exchange((2.11, 0.0, 1.5), rpm=60_000).reply.status & STATUS_STALE
        api.patch(f"/sessions/{sid}/parameters", json={"placement_position": [0, 0, 0.1]})
        assert c.exchange((2.12, 0.0, 1.5), rpm=60_000).reply.status & STATUS_STALE
    api.delete(f"/sessions/{sid}")


def _cut(client, y_mm: float, z_mm: float, ticks: int, x0: float = 2.0,
         step_mm: float = 0.003) -> list:
    """Feed along ±x (the sign of ``step_mm``) on an open stream; the replies."""
    feed = (math.copysign(FEED[0], step_mm), 0.0, 0.0)
    return [client.exchange((x0 + step_mm * k, y_mm, z_mm), rpm=60_000, velocity=feed).reply
            for k in range(ticks)]


def test_a_tool_change_mid_stream_keeps_the_stream_and_knows_the_old_groove(stack, api):
    """A 4 mm burr cuts a groove; the surgeon swaps in a 3 mm one over REST while the engine
    streams on (no hello, nothing STALE). Inside the groove the big burr cut, the small one
    feels nothing; on fresh bone it cuts as a fresh session with that burr does; swapped
    back to a 4 mm burr 0.5 mm aside, it widens the groove and cuts again; swapped for a
    fluted cylinder, it cuts with it and vibrates at its tooth frequency."""
    from burrforce.proto.messages import STATUS_STALE

    s = _session(api)
    sid = s["id"]
    small = {"radius_mm": 1.5, "shaft_radius_mm": 0.75}
    fresh = _session(api, parameters=small)
    with BurrClient(*stack.udp_address, session=fresh["id"], key=fresh["key"],
                    timeout_s=2.0) as c:
        reference = _steady(_cut(c, 4.0, 1.0, 200))
    with BurrClient(*stack.udp_address, session=sid, key=s["key"], timeout_s=2.0) as c:
        big = _steady(_cut(c, -4.0, 1.5, 300))
        assert api.patch(f"/sessions/{sid}/parameters", json=small).status_code == 200
        # Back along the groove, 0.1 mm above its floor: nothing left to cut.
        inside = _cut(c, -4.0, 1.1, 200, x0=2.897, step_mm=-0.003)
        assert max(np.linalg.norm(r.force) for r in inside[20:]) <= 0.01 * np.linalg.norm(big)
        # Fresh bone, 0.5 mm deep: the small burr's force.
        cut = _steady(_cut(c, 4.0, 1.0, 200))
        np.testing.assert_allclose(cut, reference, rtol=0.02, atol=0.01)
        assert api.patch(f"/sessions/{sid}/parameters",
                         json={"radius_mm": 2.0, "shaft_radius_mm": 1.0}).status_code == 200
        widen = _cut(c, -3.5, 1.5, 200)
        assert all(r.status & STATUS_CUTTING for r in widen[-50:])
        assert 0.1 * np.linalg.norm(big) < np.linalg.norm(_steady(widen))
        # A six-flute cylindrical cutting burr: its force, and its teeth's vibration.
        fluted = {"shape": {"kind": "cylinder", "radius_mm": 1.5, "length_mm": 4.0,
                            "end": "round"},
                  "cutter": {"kind": "fluted", "n_flutes": 6, "helix_deg": 20.0}}
        r = api.patch(f"/sessions/{sid}/parameters", json={"burr": fluted})
        assert r.status_code == 200, r.text
        view = r.json()
        assert view["burr"]["cutter"]["n_flutes"] == 6 and view["radius_mm"] == 1.5
        assert view["harmonic"] == 6.0 and view["burr_calibrated"] is False
        flutes = _cut(c, 0.0, 2.0 - 0.5, 200)  # its tip (2 mm below) 0.5 mm into fresh bone
        assert all(r.status & STATUS_CUTTING for r in flutes[-50:])
        assert np.linalg.norm(_steady(flutes)) > 0.05
        assert flutes[-1].vibration_frequency_hz == pytest.approx(6 * 60_000 / 60)
        # Re-sending its radius is harmless; resizing it is a new shape, not radius_mm.
        assert api.patch(f"/sessions/{sid}/parameters",
                         json={"radius_mm": 1.5}).status_code == 200
        r = api.patch(f"/sessions/{sid}/parameters", json={"radius_mm": 1.2})
        assert r.status_code == 422 and "give its sizes in burr.shape" in r.text
        # A user's harmonic stays while the cutter does not change.
        api.patch(f"/sessions/{sid}/parameters", json={"harmonic": 3.0})
        fluted["shape"]["length_mm"] = 5.0
        assert api.patch(f"/sessions/{sid}/parameters",
                         json={"burr": fluted}).json()["harmonic"] == 3.0
        replies = inside + widen + flutes
        assert not any(r.status & STATUS_STALE for r in replies)
        assert c.counters["hellos"] == 1 and c.counters["timeouts"] == 0
    for session in (sid, fresh["id"]):
        api.delete(f"/sessions/{session}")


def test_us_set_at_creation_stays_on_its_material_across_a_reset(api):
    s = _session(api, bone={"source": "phantom:layered", "voxel_mm": 0.25},
                 parameters={"us_n_mm2": 5000.0})
    sid = s["id"]
    assert api.patch(f"/sessions/{sid}/parameters",
                     json={"primary_material": 2, "k": 0.5}).status_code == 200
    api.post(f"/sessions/{sid}/reset")
    table = {m["label"]: m for m in api.get(f"/sessions/{sid}/materials").json()}
    assert table[1]["us_n_mm2"] == 5000.0 and table[2]["k"] == 0.5
    assert table[2]["us_n_mm2"] != 5000.0
    api.delete(f"/sessions/{sid}")


def test_deltas_answer_while_a_client_streams(stack, api):
    import threading

    s = _session(api)
    stop = threading.Event()

    def cut():
        with BurrClient(*stack.udp_address, session=s["id"], key=s["key"],
                        timeout_s=2.0) as c:
            k = 0
            while not stop.is_set() and k < 5000:
                c.exchange((2.0 + 0.003 * k, 0.0, 1.5), rpm=60_000, velocity=FEED)
                k += 1
    t = threading.Thread(target=cut)
    t.start()
    try:
        time.sleep(0.3)
        for _ in range(5):
            r = api.get(f"/sessions/{s['id']}/deltas", params={"since": 0})
            assert r.status_code == 200, r.text
            assert decode_delta(r.content)["count"] > 0
            assert api.get(f"/sessions/{s['id']}/export/volume",
                           params={"format": "npy"}).status_code == 200
    finally:
        stop.set()
        t.join(30)
    api.delete(f"/sessions/{s['id']}")


def _npy(api, sid: int, what: str = "remaining") -> tuple[np.ndarray, dict]:
    import io

    r = api.get(f"/sessions/{sid}/export/volume", params={"format": "npy", "what": what})
    assert r.status_code == 200, r.text
    return np.load(io.BytesIO(r.content)), r.headers


def _brick_copy(api, sid: int, copy: np.ndarray, since, generation, max_bricks=4096):
    """A client bringing its copy up to the bone with deltas (every page)."""
    from burrforce.server.bone.deltas import apply_delta

    first = None
    for _ in range(100):
        params = {"max_bricks": max_bricks}
        params.update({k: v for k, v in (("since", since), ("generation", generation))
                       if v is not None})
        r = api.get(f"/sessions/{sid}/deltas", params=params)
        assert r.status_code == 200, r.text
        d = decode_delta(r.content)
        first = first or d
        if d["full"] and tuple(d["grid_shape"]) != copy.shape:
            copy = np.zeros(d["grid_shape"], np.uint8)
        since, generation = apply_delta(copy, d), d["generation"]
        assert since is not None
        if d["complete"]:
            return copy, since, generation, first
    pytest.fail("paging did not finish")


def test_a_bone_version_beyond_64_bits_is_a_422(api):
    """schemathesis found a 500 for since=227629129482688010387456 (a bone version is an
    int64)."""
    s = _session(api)
    for path in ("deltas", "mesh"):
        r = api.get(f"/sessions/{s['id']}/{path}", params={"since": 1 << 80})
        assert r.status_code == 422 and "less than or equal" in r.text, r.text
    api.delete(f"/sessions/{s['id']}")


def test_a_replaced_bone_has_a_new_generation_and_old_copies_get_full_deltas(stack, api):
    s = _session(api)
    sid = s["id"]
    generation = s["bone"]["generation"]
    assert isinstance(generation, int) and generation > 0
    _groove(stack, s, 0.0, 150)
    copy, _ = _npy(api, sid)
    copy, version, generation, d = _brick_copy(api, sid, copy * 0, None, generation)
    assert d["full"] and version > 0
    np.testing.assert_array_equal(copy, _npy(api, sid)[0])
    snap = api.post(f"/sessions/{sid}/snapshot", json={"name": f"gen-{sid}"})
    assert snap.status_code == 201, snap.text
    with np.load(stack.plane.roots.snapshots / f"gen-{sid}.bone.npz") as z:
        meta = json.loads(z["meta"].tobytes().decode())
    assert (meta["generation"], meta["bone_version"]) == (generation, version)
    seen = {generation}
    for how, replace in (
            ("reset", lambda: api.post(f"/sessions/{sid}/reset")),
            ("load", lambda: api.put(f"/sessions/{sid}/bone",
                                     json={"source": "library:block.bone.npz"})),
            ("restore", lambda: api.post(f"/sessions/{sid}/restore",
                                         json={"snapshot": f"gen-{sid}"}))):
        r = replace()
        assert r.status_code in (200, 202), (how, r.text)
        new = api.get(f"/sessions/{sid}").json()["bone"]["generation"]
        assert new not in seen, how
        seen.add(new)
        if how != "restore":
            _groove(stack, s, 3.0, 150)  # carve the new bone past the old copy, or not
        # The old (generation, version) pair: a full answer that makes the old copy exact.
        copy, version, generation, d = _brick_copy(api, sid, copy, version, generation,
                                                   max_bricks=1 << 16)
        assert d["full"] and d["generation"] == generation == new, how
        now, headers = _npy(api, sid)
        np.testing.assert_array_equal(copy, now, err_msg=how)
        assert headers["x-burrforce-bone-generation"] == str(new)
        assert headers["x-burrforce-bone-version"] == str(version)
        # The current pair: an ordinary (empty) delta.
        d = decode_delta(api.get(f"/sessions/{sid}/deltas", params={
            "since": version, "generation": generation}).content)
        assert not d["full"] and d["count"] == 0
    # NRRD exports name their generation in the file.
    r = api.get(f"/sessions/{sid}/export/volume", params={"format": "nrrd"})
    assert f"burrforce_bone_generation:={generation}\n".encode() in r.content[:2000]
    # Without a generation a client gets what it always did.
    r = api.get(f"/sessions/{sid}/deltas", params={"since": 10**9})
    assert r.status_code == 422 and "newer than the bone" in r.text
    assert api.get(f"/sessions/{sid}/deltas", params={"generation": -1}).status_code == 422
    api.delete(f"/sessions/{sid}")


def test_a_bone_export_loads_back_with_its_materials(stack, api):
    s = _session(api, bone={"source": "phantom:layered", "voxel_mm": VOXEL_MM})
    sid = s["id"]
    assert api.patch(f"/sessions/{sid}/materials/2",
                     json={"us_n_mm2": 300.0, "forbidden": True}).status_code == 200
    _groove(stack, s, 0.0, 150, z_mm=1.0)
    r = api.get(f"/sessions/{sid}/export/volume", params={"format": "bone"})
    assert r.status_code == 200, r.text
    assert r.headers["x-burrforce-bone-generation"] == str(s["bone"]["generation"])
    up = api.post("/uploads", params={"filename": "carved.bone.npz"}, content=r.content)
    assert up.status_code == 201, up.text
    t = _session(api, bone={"source": up.json()["source"]})
    assert t["bone"]["generation"] != s["bone"]["generation"]
    labels, _ = _npy(api, sid, "labels")
    assert set(np.unique(labels).tolist()) >= {1, 2}
    np.testing.assert_array_equal(_npy(api, t["id"], "labels")[0], labels)
    np.testing.assert_array_equal(_npy(api, t["id"])[0], _npy(api, sid)[0])  # the carving
    assert _npy(api, sid)[0].sum() < _npy(api, sid, "density")[0].sum()
    assert api.get(f"/sessions/{t['id']}/materials").json() == \
        api.get(f"/sessions/{sid}/materials").json()
    bad = api.get(f"/sessions/{sid}/export/volume", params={"format": "bone", "what": "labels"})
    assert bad.status_code == 422 and "leave what out" in bad.text
    api.delete(f"/sessions/{sid}")
    api.delete(f"/sessions/{t['id']}")


# -- haptic output ----------------------------------------------------------------------------
def test_a_device_profile_turns_on_the_coupled_output(stack, api):
    """A device profile makes the output coupled: the reply carries the coupling model and
    the force stays within the device's limits; coupling false keeps the raw force (held to
    the device's limits); device none is the unlimited raw force again."""
    s = _session(api)
    sid = s["id"]
    raw = _groove(stack, s, 0.0, 150)
    assert raw[-1].coupling_stiffness == 0.0 and raw[-1].proxy_position == (0.0, 0.0, 0.0)

    r = api.patch(f"/sessions/{sid}/parameters", json={"device": "touch"})
    assert r.status_code == 200, r.text
    assert r.json()["device"] == "touch" and r.json()["device_limits"]["max_force_N"] == 3.3
    assert api.get(f"/sessions/{sid}").json()["output"] == "coupled"
    coupled = _groove(stack, s, 4.0, 300)
    last = coupled[-1]
    assert last.coupling_stiffness == pytest.approx(0.4)  # si_mm: N/mm
    assert last.coupling_damping == pytest.approx(0.002)
    assert all(math.hypot(*c.force) <= 3.3 + 1e-9 for c in coupled)
    # The proxy cuts where the hand holds it: near the device, at the surface or below.
    assert abs(last.proxy_position[0] - (2.0 + 0.003 * 299)) < 1.0

    r = api.patch(f"/sessions/{sid}/parameters",
                  json={"device_limits": {"max_force_N": 0.05}})
    assert r.json()["device"] == "custom" and r.json()["device_limits"]["max_force_N"] == 0.05
    api.put(f"/sessions/{sid}/features", json={**api.get(
        f"/sessions/{sid}/features").json(), "coupling": False})
    assert api.get(f"/sessions/{sid}").json()["output"] == "raw"
    limited = _groove(stack, s, -4.0, 150)
    assert limited[-1].coupling_stiffness == 0.0
    assert max(math.hypot(*c.force) for c in limited) <= 0.05 + 1e-9
    assert limited[-1].status & STATUS_CLAMPED

    assert api.patch(f"/sessions/{sid}/parameters",
                     json={"device": "none"}).json()["device"] is None
    bad = api.patch(f"/sessions/{sid}/parameters",
                    json={"device": "none", "device_limits": {"max_force_N": 1.0}})
    assert bad.status_code == 422 and "device_limits" in bad.text
    assert api.patch(f"/sessions/{sid}/parameters",
                     json={"device": "phantom-omni"}).status_code == 422
    api.delete(f"/sessions/{sid}")


def test_restart_stream_over_rest_ends_the_stream_and_the_client_says_hello(stack, api):
    """POST restart-stream ends the stream: the client's next POSE gets WRONG_STREAM, its
    exchange says hello and goes on in a new stream (one call for the user); a datagram of
    the old stream replayed afterwards is refused, never ticked."""
    import socket

    from burrforce.proto.codec import decode_server_message
    from burrforce.proto.messages import WRONG_STREAM

    s = _session(api)
    sid = s["id"]
    with BurrClient(*stack.udp_address, session=sid, key=s["key"], timeout_s=2.0) as c:
        c.exchange((2.0, 0.0, 1.5), rpm=60_000, velocity=FEED)
        old = c.rules.stream
        old_pose = c.rules.datagram((2.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True,
                                    FEED, 0, None)[1]  # captured, never sent
        assert api.post(f"/sessions/{sid}/restart-stream").status_code == 204
        r = c.exchange((2.003, 0.0, 1.5), rpm=60_000, velocity=FEED)
        assert r.reply.error == 0 and c.rules.stream not in (0, old)
        assert (c.counters["wrong_stream"], c.counters["streams"], c.counters["hellos"]) == (
            1, 2, 2)
    state = api.get(f"/sessions/{sid}/state").json()
    assert state["stream"] == c.rules.stream and state["wrong_stream"] == 1
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as replay:
        replay.connect(stack.udp_address)
        replay.settimeout(2.0)
        replay.send(old_pose)
        notice = decode_server_message(replay.recv(2048))
    assert (notice.error, notice.stream) == (WRONG_STREAM, old)
    after = api.get(f"/sessions/{sid}/state").json()
    assert (after["bone_version"], after["accepted"]) == (state["bone_version"],
                                                          state["accepted"])
    assert after["wrong_stream"] == 2
    api.delete(f"/sessions/{sid}")
