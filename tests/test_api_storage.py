"""Storage the user can see and clean up: listing, downloading and deleting uploads, snapshots
and recordings, names that would leave their folder, and the data directory's budget. Against
the real stack (hot loop, uvicorn, httpx, UDP clients cutting, real files)."""

from __future__ import annotations

import argparse
import io
import tarfile
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.client import BurrClient
from burrforce.client.rest import BurrRest, RestError
from burrforce.server.api.config import ServeConfig, from_toml, load_config, parse_size_bytes
from burrforce.server.api.stack import ServerStack
from burrforce.server.api.storage import RECORDING_MARGIN_BYTES
from burrforce.server.record import replay

TOKEN = "test-token-storage-0123456789"
#: Coarse, so bones, snapshots and recordings stay small and fast.
VOXEL_MM = 0.5
FEED = (3.0, 0.0, 0.0)
BONE = {"source": "phantom:workpiece", "voxel_mm": VOXEL_MM}


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path_factory.mktemp("data"),
                         upload_max_mb=4.0)
    with ServerStack(config, TOKEN) as s:
        yield s


@pytest.fixture(scope="module")
def api(stack):
    with httpx.Client(base_url=stack.url + "/v1", timeout=120.0,
                      headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        yield client


@contextmanager
def budget(stack, budget_bytes: int):
    """The server's budget set to ``budget_bytes`` for a while (read at every write)."""
    storage = stack.plane.storage
    before = storage.budget_bytes
    storage.budget_bytes = budget_bytes
    try:
        yield
    finally:
        storage.budget_bytes = before


def _session(api, **body) -> dict:
    body.setdefault("bone", BONE)
    r = api.post("/sessions", json=body)
    assert r.status_code == 201, r.text
    return r.json()


def _groove(stack, s: dict, ticks: int, y_mm: float = 0.0) -> None:
    with BurrClient(*stack.udp_address, session=s["id"], key=s.get("key"),
                    timeout_s=2.0) as c:
        for k in range(ticks):
            c.exchange((2.0 + 0.003 * k, y_mm, 1.5), rpm=60_000, velocity=FEED)


def _upload(api, data: bytes, filename: str = "cube.npy") -> dict:
    r = api.post("/uploads", params={"filename": filename}, content=data)
    assert r.status_code == 201, r.text
    return r.json()


def _cube_bytes(n: int = 20) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.full((n, n, n), 255, dtype=np.uint8))
    return buf.getvalue()


def _detail(r: httpx.Response) -> str:
    return str(r.json()["detail"])


# -- usage ------------------------------------------------------------------------------------
def test_storage_reports_each_kind_and_leaves_the_journal_out_of_the_budget(stack, api):
    journal = stack.plane.data_dir / "journal"
    journal.mkdir(exist_ok=True)
    (journal / "entries.log").write_bytes(b"j" * 5000)
    before = api.get("/storage").json()
    assert before["kinds"]["journal"] == {"bytes": 5000, "items": 1, "counted": False}
    data = _cube_bytes()
    up = _upload(api, data)
    after = api.get("/storage").json()
    assert after["kinds"]["uploads"]["bytes"] == before["kinds"]["uploads"]["bytes"] + len(data)
    assert after["kinds"]["uploads"]["items"] == before["kinds"]["uploads"]["items"] + 1
    assert after["used_bytes"] == sum(after["kinds"][k]["bytes"] for k in
                                      ("uploads", "snapshots", "recordings", "exports"))
    assert after["budget_bytes"] == 20 << 30
    assert after["free_bytes"] == after["budget_bytes"] - after["used_bytes"] \
        - after["reserved_bytes"]
    assert after["disk_free_bytes"] > 0
    api.delete(f"/uploads/{up['id']}")


# -- uploads ----------------------------------------------------------------------------------
def test_uploads_list_download_and_delete_saying_who_used_them(api):
    data = _cube_bytes()
    up = _upload(api, data)
    listed = {u["id"]: u for u in api.get("/uploads").json()}[up["id"]]
    assert listed["bytes"] == len(data) and listed["source"] == up["source"]
    assert listed["created"] > 0 and listed["in_use_by"] == []
    assert api.get(f"/uploads/{up['id']}").content == data
    s = _session(api, bone={"source": up["source"], "kind": "density",
                            "spacing_mm": [0.5, 0.5, 0.5]})
    assert {u["id"]: u for u in api.get("/uploads").json()}[up["id"]]["in_use_by"] == [s["id"]]
    r = api.delete(f"/uploads/{up['id']}")  # a live session's bone: not without force
    assert r.status_code == 409 and "force=true" in _detail(r) and str(s["id"]) in _detail(r)
    r = api.delete(f"/uploads/{up['id']}?force=true")
    assert r.status_code == 200, r.text
    gone = r.json()
    assert gone["in_use_by"] == [s["id"]] and gone["bytes"] == len(data)
    assert f"session {s['id']}" in gone["note"] and "reset will fail" in gone["note"]
    # The session keeps the bone it loaded.
    assert api.get(f"/sessions/{s['id']}").json()["state"] == "ready"
    assert up["id"] not in {u["id"] for u in api.get("/uploads").json()}
    for r in (api.get(f"/uploads/{up['id']}"), api.delete(f"/uploads/{up['id']}")):
        assert r.status_code == 404 and up["id"] in _detail(r)
    api.delete(f"/sessions/{s['id']}")


# -- snapshots --------------------------------------------------------------------------------
def test_snapshots_list_download_and_delete(stack, api):
    s = _session(api)
    _groove(stack, s, 40)
    snap = api.post(f"/sessions/{s['id']}/snapshot", json={"name": "keep-me"}).json()
    listed = {x["name"]: x for x in api.get("/snapshots").json()}["keep-me"]
    assert listed["bytes"] == snap["bytes"] and listed["in_use_by"] == []
    content = api.get("/snapshots/keep-me").content
    assert content[:2] == b"PK" and len(content) == snap["bytes"]
    t = _session(api, bone={"source": "snapshot:keep-me"})
    assert api.delete("/snapshots/keep-me.bone.npz").status_code == 409
    r = api.delete("/snapshots/keep-me.bone.npz?force=true")
    assert r.status_code == 200, r.text
    assert r.json()["deleted"] == "keep-me" and r.json()["in_use_by"] == [t["id"]]
    assert "snapshot:keep-me" in r.json()["note"]
    assert "keep-me" not in {x["name"] for x in api.get("/snapshots").json()}
    r = api.delete("/snapshots/keep-me")
    assert r.status_code == 404 and "keep-me" in _detail(r)
    api.delete(f"/sessions/{s['id']}")
    api.delete(f"/sessions/{t['id']}")


# -- recordings -------------------------------------------------------------------------------
def test_a_recording_downloads_as_a_tar_that_replays_and_is_not_deleted_while_written(
        stack, api, tmp_path):
    s = _session(api)
    sid = s["id"]
    assert api.post(f"/sessions/{sid}/recording", json={"name": "run-1"}).status_code == 201
    _groove(stack, s, 120)
    listed = {x["name"]: x for x in api.get("/recordings").json()}["run-1.burrrec"]
    assert listed["recording_session"] == sid and not listed["complete"]
    for r in (api.delete("/recordings/run-1"), api.get("/recordings/run-1.burrrec")):
        assert r.status_code == 409, r.text
        assert f"DELETE /v1/sessions/{sid}/recording" in _detail(r)
    assert (stack.plane.recordings_dir / "run-1.burrrec").is_dir()
    api.delete(f"/sessions/{sid}/recording")

    r = api.get("/recordings/run-1")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-tar"
    assert int(r.headers["content-length"]) == len(r.content)
    assert "run-1.burrrec.tar" in r.headers["content-disposition"]
    with tarfile.open(fileobj=io.BytesIO(r.content)) as tar:
        names = tar.getnames()
        tar.extractall(tmp_path, filter="data")
    assert "run-1.burrrec/meta.json" in names and "run-1.burrrec/summary.json" in names
    report = replay(tmp_path / "run-1.burrrec")
    assert report.reproduced and report.ticks == 120
    listed = {x["name"]: x for x in api.get("/recordings").json()}["run-1.burrrec"]
    assert listed["complete"] and listed["recording_session"] is None
    assert listed["modified"] >= listed["created"] > 0

    r = api.delete("/recordings/run-1.burrrec")
    assert r.status_code == 200 and r.json()["bytes"] == listed["bytes"]
    assert not (stack.plane.recordings_dir / "run-1.burrrec").exists()
    r = api.get("/recordings/run-1")
    assert r.status_code == 404 and "run-1.burrrec" in _detail(r)
    api.delete(f"/sessions/{sid}")


# -- names --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["uploads", "snapshots", "recordings", "exports"])
@pytest.mark.parametrize("name", [
    "..%2Fbait.bone.npz", "..%2F..%2Fbait.bone.npz", "%2Fetc%2Fpasswd", "..", "..%2F",
    "bait%00.bone.npz", "%2E%2E%2Fbait", "a%5C..%5Cbait", ".hidden",
])
def test_names_that_leave_their_folder_are_refused(stack, api, kind, name):
    # Bait one level up: a traversal that worked would list, read or delete it.
    bait = stack.plane.data_dir / "bait.bone.npz"
    bait.write_bytes(b"PK bait")
    for method in ("DELETE",) if kind == "exports" else ("GET", "DELETE"):  # not served
        r = api.request(method, f"/{kind}/{name}")
        assert 400 <= r.status_code < 500, (method, r.status_code, r.text)
        assert r.status_code != 200
    assert bait.read_bytes() == b"PK bait"


def test_a_bad_name_says_what_is_wrong(api):
    r = api.delete("/snapshots/..%2Fbait")
    assert r.status_code == 400 and "plain name" in _detail(r)
    r = api.get("/uploads/not-an-id")
    assert r.status_code == 400 and "16 hex digits" in _detail(r)
    r = api.get("/uploads/%2Fetc%2Fpasswd")
    assert r.status_code == 400 and "plain name" in _detail(r)


@pytest.mark.parametrize("filename", ["cube\x00.npy", "cube.npy\x00.sh", "two\nlines.npy",
                                      "\x1b[2Jcube.npy", "cube\x7f.npy", "cube\x85.npy"])
def test_an_upload_filename_with_control_characters_is_refused(stack, api, filename):
    uploads = stack.plane.roots.uploads
    before = sorted(p.name for p in uploads.iterdir())
    r = api.post("/uploads", params={"filename": filename}, content=_cube_bytes(4))
    assert r.status_code == 422, r.text
    assert "control characters" in r.text and "U+00" in r.text
    assert filename not in r.text  # not echoed back
    assert sorted(p.name for p in uploads.iterdir()) == before


# -- the budget ---------------------------------------------------------------------------------
def _used(api) -> int:
    u = api.get("/storage").json()
    return u["used_bytes"] + u["reserved_bytes"]


def test_an_upload_over_the_budget_gets_413_saying_what_to_do(stack, api):
    data = _cube_bytes()
    uploads = stack.plane.roots.uploads
    before = sorted(p.name for p in uploads.iterdir())
    with budget(stack, _used(api) + len(data) - 1):
        r = api.post("/uploads", params={"filename": "cube.npy"}, content=data)
        assert r.status_code == 413, r.text
        detail = _detail(r)
        assert "budget" in detail and "GET /v1/storage" in detail
        assert "DELETE /v1/uploads/ID" in detail and "used" in detail
        # Without a length the stream is cut at the budget.
        r = api.post("/uploads", params={"filename": "cube.npy"},
                     content=iter([data[:4000], data[4000:]]))
        assert r.status_code == 413 and "budget" in _detail(r)
        assert sorted(p.name for p in uploads.iterdir()) == before  # no partial file left
    with budget(stack, _used(api) + len(data)):
        up = _upload(api, data)  # exactly fits
    api.delete(f"/uploads/{up['id']}")


def test_snapshots_exports_and_recordings_over_the_budget_get_507(stack, api):
    s = _session(api)
    sid = s["id"]
    held = _upload(api, _cube_bytes(8))  # something stored: a budget of 0 would be none
    with budget(stack, _used(api)):  # full
        for r in (api.post(f"/sessions/{sid}/snapshot", json={"name": "too-much"}),
                  api.get(f"/sessions/{sid}/export/volume"),
                  api.get(f"/sessions/{sid}/export/mesh"),
                  api.post(f"/sessions/{sid}/recording", json={"name": "too-much"})):
            assert r.status_code == 507, r.text
            assert "budget" in _detail(r) and "GET /v1/storage" in _detail(r)
    with budget(stack, _used(api) + 100):  # room, but not for a whole snapshot
        r = api.post(f"/sessions/{sid}/snapshot", json={"name": "too-much"})
        assert r.status_code == 507 and "the snapshot" in _detail(r)
        r = api.post(f"/sessions/{sid}/recording", json={"name": "too-much"})
        assert r.status_code == 507, r.text
    assert not (stack.plane.roots.snapshots / "too-much.bone.npz").exists()
    assert not (stack.plane.recordings_dir / "too-much.burrrec").exists()
    assert list((stack.plane.data_dir / "exports").iterdir()) == []
    api.delete(f"/uploads/{held['id']}")
    api.delete(f"/sessions/{sid}")


def test_a_recording_is_capped_by_the_room_left_and_stops_cleanly_there(stack, api):
    s = _session(api)
    sid = s["id"]
    room = 150_000
    limit = _used(api) + room
    with budget(stack, limit):
        r = api.post(f"/sessions/{sid}/recording", json={"name": "capped"})
        assert r.status_code == 201, r.text
        snapshot_bytes = (stack.plane.recordings_dir / "capped.burrrec"
                          / "start.bone.npz").stat().st_size
        cap = r.json()["max_bytes"]
        assert cap == room - snapshot_bytes - RECORDING_MARGIN_BYTES
        # The room it holds is not free for others.
        u = api.get("/storage").json()
        assert u["reserved_bytes"] == cap and u["free_bytes"] < RECORDING_MARGIN_BYTES
        _groove(stack, s, 400)  # 400 rows × 472 bytes: more than the cap
        status = api.get(f"/sessions/{sid}/recording").json()
        assert "max_bytes" in status["stopped_reason"]
        stopped = api.delete(f"/sessions/{sid}/recording").json()
        assert 0 < stopped["rows_written"] < 400
        u = api.get("/storage").json()
        assert u["used_bytes"] <= limit and u["reserved_bytes"] == 0
    report = replay(stack.plane.recordings_dir / "capped.burrrec")
    assert report.reproduced and report.ticks == stopped["rows_written"]
    api.delete("/recordings/capped")
    api.delete(f"/sessions/{sid}")


# -- exports ------------------------------------------------------------------------------------
def test_an_export_left_by_a_cut_off_download_is_listed_and_deleted(stack, api, tmp_path):
    exports = stack.plane.data_dir / "exports"
    s = _session(api)
    # A download whose client went away mid-way: the server never got to delete the file.
    with api.stream("GET", f"/sessions/{s['id']}/export/volume",
                    params={"format": "npy"}) as r:
        assert r.status_code == 200
        left = sorted(exports.iterdir())
    assert len(left) == 1 and left[0].stat().st_size > 0
    left[0].with_name("export-0123456789abcdef.nrrd").write_bytes(b"NRRD0004 partial")
    listed = {e["name"]: e for e in api.get("/exports").json()}
    assert listed["export-0123456789abcdef.nrrd"]["bytes"] == 16
    assert api.get("/storage").json()["kinds"]["exports"]["list"] == "/v1/exports"
    with BurrRest(stack.url, TOKEN) as rest:
        answer = rest.delete_export("export-0123456789abcdef.nrrd")
        assert answer == {"deleted": "export-0123456789abcdef.nrrd", "kind": "export",
                          "bytes": 16, "in_use_by": [], "note": None}
        with pytest.raises(RestError) as err:
            rest.delete_export("export-0123456789abcdef.nrrd")
        assert err.value.status == 404
    for name in {e["name"] for e in api.get("/exports").json()}:
        # 404: the cut-off download's own clean-up came first after all.
        assert api.delete(f"/exports/{name}").status_code in (200, 404)
    assert api.get("/exports").json() == [] and not any(exports.iterdir())
    api.delete(f"/sessions/{s['id']}")


def test_a_starting_server_removes_what_a_killed_one_left_unfinished(tmp_path):
    """Temporaries of writes under way (and those older servers named otherwise) and exports
    no server serves any more; the user's files stay."""
    stack = ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path), TOKEN,
                        journal=False)
    leftovers = ["exports/export-ddn13xab.npy", "exports/export-0123456789abcdef.bone.npz",
                 "uploads/.0123456789abcdef.npy.k3j4h5g6.part", "uploads/.upload-abc123",
                 "snapshots/.burrforce-x1y2z3.tmp", "snapshots/.a.bone.npz.q1w2e3r4.part",
                 "recordings/.x.burrrec.a1b2c3d4.part", ".bone-generation.4242.tmp"]
    kept = ["uploads/0123456789abcdef.npy", "snapshots/a.bone.npz",
            "recordings/r.burrrec/chunk-000000.npy.part", "bone-generation"]
    for rel in leftovers + kept:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"x" * 10)
    with stack:
        for rel in leftovers:
            assert not (tmp_path / rel).exists(), rel
        for rel in kept:  # a torn chunk stays: the recording's reader reports it
            assert (tmp_path / rel).exists(), rel


# -- the Python client --------------------------------------------------------------------------
def test_the_client_lists_downloads_and_deletes_every_kind(stack, api, tmp_path):
    data = _cube_bytes(12)
    (tmp_path / "small.npy").write_bytes(data)
    with BurrRest(stack.url, TOKEN) as rest:
        usage = rest.storage()
        assert usage["budget_bytes"] == 20 << 30 and "uploads" in usage["kinds"]
        source = rest.upload(tmp_path / "small.npy")
        assert source in {u["source"] for u in rest.uploads()}
        got = rest.download_upload(source, tmp_path / "back.npy")
        assert got.read_bytes() == data
        assert rest.delete_upload(source)["bytes"] == len(data)
        with pytest.raises(RestError) as err:
            rest.delete_upload(source)
        assert err.value.status == 404 and source.split(":")[1] in err.value.detail

        s = rest.create_session("phantom:workpiece", voxel_mm=VOXEL_MM)
        rest.snapshot(s["id"], "client-snap")
        path = rest.download_snapshot("snapshot:client-snap", tmp_path / "c.bone.npz")
        assert path.read_bytes()[:2] == b"PK"
        assert rest.delete_snapshot("client-snap")["deleted"] == "client-snap"
        with pytest.raises(RestError) as err:
            rest.delete_snapshot("../client-snap")
        assert err.value.status == 400

        rest.start_recording(s["id"], "client-rec")
        _groove(stack, s, 30)
        with pytest.raises(RestError) as err:
            rest.delete_recording("client-rec")
        assert err.value.status == 409
        rest.stop_recording(s["id"])
        listed = {r["name"]: r for r in rest.recordings()}["client-rec.burrrec"]
        tar_path = rest.download_recording("client-rec", tmp_path / "rec.tar")
        with tarfile.open(tar_path) as tar:
            assert "client-rec.burrrec/meta.json" in tar.getnames()
        assert rest.delete_recording("client-rec.burrrec")["bytes"] == listed["bytes"]
        assert "client-rec.burrrec" not in {r["name"] for r in rest.recordings()}
        rest.delete_session(s["id"])


# -- configuration -----------------------------------------------------------------------------
@given(st.integers(0, 1 << 20), st.sampled_from([("", 1), ("K", 1 << 10), ("MiB", 1 << 20),
                                                 ("gb", 1 << 30), ("T", 1 << 40)]))
def test_sizes_parse_in_binary_units(n, unit):
    suffix, factor = unit
    assert parse_size_bytes(f"{n}{suffix}") == n * factor


@pytest.mark.parametrize("text", ["", "lots", "-1", "1Q", "1.5.5", "GiB", "5ib"])
def test_a_bad_size_says_so(text):
    with pytest.raises(ValueError, match="not a size"):
        parse_size_bytes(text)


def test_the_budget_comes_from_toml_environment_and_flag(tmp_path):
    toml = tmp_path / "serve.toml"
    toml.write_text('[server]\ndata_budget_bytes = "2GiB"\n')
    assert from_toml(toml).data_budget_bytes == 2 << 30
    toml.write_text("[server]\ndata_budget_bytes = 0\n")
    assert from_toml(toml).data_budget_bytes == 0
    env = {"BURRFORCE_DATA_BUDGET_BYTES": "500M"}
    assert load_config(None, environ=env).data_budget_bytes == 500 << 20
    with pytest.raises(ValueError, match=r"BURRFORCE_DATA_BUDGET_BYTES.*not a size"):
        load_config(None, environ={"BURRFORCE_DATA_BUDGET_BYTES": "lots"})
    with pytest.raises(ValueError, match="non-negative"):
        ServeConfig(data_budget_bytes=-1)

    from burrforce.server.cli import serve

    parser = argparse.ArgumentParser()
    serve.add_parser(parser.add_subparsers())
    assert parser.parse_args(["serve", "--data-budget", "1G"]).data_budget == 1 << 30
    with pytest.raises(SystemExit):
        parser.parse_args(["serve", "--data-budget", "plenty"])
