"""A full disk is an answer, not a crash: a real ``burrforce serve`` whose data directory is a
20 MB tmpfs, filled up by another file. Every write route answers 507 saying what it needed
and what is free, and leaves no file behind (nothing 0-byte, nothing partial); ``/v1/storage``
reports the disk's real free space; a recording is granted no more than the disk has, and one
the disk fills up under ends complete with the rows that fit.

Mounting needs root, as CI runs the tests (``support.tmpfs``); elsewhere these are skipped
with the reason, and ``BURRFORCE_STRICT_SKIPS=1`` turns that skip into a failure.

The journal (``journal/``) is another module's and is left out of the file comparisons.
"""

from __future__ import annotations

import time
from pathlib import Path

import httpx
import pytest

from burrforce.client import BurrClient
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.record import read_recording, replay
from burrforce.server.record.format import SUMMARY_NAME
from support.tmpfs import fill, free_bytes, small_tmpfs

TOKEN = "full-disk-token-0123456789abcdef"
FILLER = "filler"
#: A cube too large for a page of room: 300 kB of npy.
UPLOAD = b"\x93NUMPY" + bytes(300_000)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    folder = tmp_path_factory.mktemp("full-disk")
    with small_tmpfs(folder / "data", "20m") as data:
        serve = spawn_serve(folder, "--bone", "phantom:workpiece", "--voxel-mm", "0.2",
                            "--token", TOKEN)
        try:
            yield serve, data
        finally:
            code, out = serve.stop()
            # Not one traceback: every full-disk failure was answered.
            assert code == 0 and "Traceback" not in out, out[-4000:]


@pytest.fixture()
def api(served):
    serve, _ = served
    with httpx.Client(base_url=serve.connection.http_url.rstrip("/") + "/v1", timeout=120.0,
                      headers={"Authorization": f"Bearer {TOKEN}"}) as client:
        yield client


@pytest.fixture()
def data(served):
    """The data directory, with the filler removed after the test."""
    _, data = served
    yield data
    (data / FILLER).unlink(missing_ok=True)


def _files(data: Path) -> set[str]:
    """Everything under the data directory but the journal and the filler."""
    out = set()
    for p in data.rglob("*"):
        rel = p.relative_to(data)
        if rel.parts[0] not in ("journal", FILLER):
            out.add(str(rel))
    return out


def _cut(serve, n: int, x0: float = 3.0) -> int:
    """A groove in the workpiece; returns the replies that came back."""
    c = serve.connection
    got = 0
    with BurrClient(c.host, c.udp_port, c.session, c.key_hex, timeout_s=1.0) as client:
        for i in range(n):
            try:
                client.exchange((x0 + 0.005 * i, 0.0, -0.6), rpm=60_000.0, timeout_s=0.5)
                got += 1
            except TimeoutError:
                pass
    return got


def _chunked(data: bytes, step: int = 32 << 10):
    """The body without a Content-Length: its size is known only as it arrives."""
    for i in range(0, len(data), step):
        yield data[i:i + step]


def _writes(api, sid: int) -> dict[str, httpx.Response]:
    """Every write route once."""
    out = {
        "upload": api.post("/uploads", params={"filename": "cube.npy"}, content=UPLOAD),
        "upload, chunked": api.post("/uploads", params={"filename": "cube.npy"},
                                    content=_chunked(UPLOAD)),
        "snapshot": api.post(f"/sessions/{sid}/snapshot", json={"name": "full"}),
        "recording": api.post(f"/sessions/{sid}/recording", json={"name": "full"}),
    }
    for fmt in ("npy", "nrrd", "bone"):
        out[f"export {fmt}"] = api.get(f"/sessions/{sid}/export/volume",
                                       params={"format": fmt})
    for fmt in ("stl", "ply", "obj"):
        out[f"export {fmt}"] = api.get(f"/sessions/{sid}/export/mesh", params={"format": fmt})
    return out


@pytest.mark.parametrize("room", [0, 4096], ids=["no room", "one page"])
def test_every_write_route_on_a_full_disk_answers_507_and_leaves_no_file(served, api, data,
                                                                          room):
    """With no room, each is refused before it writes; with one page, those whose size is not
    known beforehand (a chunked upload, a snapshot, nrrd/bone/ply/obj, a recording's start
    snapshot) are refused when the disk refuses them under way, and what they wrote goes."""
    serve, _ = served
    _cut(serve, 50)  # a carved bone: something to write
    fill(data, leave_bytes=room)
    assert free_bytes(data) == room
    before = _files(data)
    answers = _writes(api, serve.connection.session)
    for what, r in answers.items():
        assert r.status_code == 507, (what, r.status_code, r.text[:300])
        detail = r.json()["detail"]
        assert "disk" in detail and "free" in detail, (what, detail)
        assert "GET /v1/storage" in detail, (what, detail)  # where to look, what to delete
        if what in ("upload", "export npy", "export stl"):  # sizes known beforehand
            assert "needs" in detail, (what, detail)
    assert _files(data) == before  # not a 0-byte file, not a partial one, not a temporary
    assert api.get("/exports").json() == []


def test_storage_reports_the_disks_free_space(served, api, data):
    budget = api.get("/storage").json()
    assert budget["budget_bytes"] == 20 << 30  # the default: far beyond a 20 MB disk
    assert budget["free_bytes"] <= budget["disk_free_bytes"] <= 20 << 20
    assert abs(budget["free_bytes"] - free_bytes(data)) <= 64 << 10  # the journal writes
    fill(data)
    full = api.get("/storage").json()
    assert full["disk_free_bytes"] == 0 and full["free_bytes"] == 0


def test_a_recording_is_granted_no_more_than_the_disk_has_and_stops_cleanly(served, api,
                                                                            data):
    serve, _ = served
    sid = serve.connection.session
    fill(data, leave_bytes=1 << 20)
    r = api.post(f"/sessions/{sid}/recording", json={"name": "granted"})
    assert r.status_code == 201, r.text
    granted = r.json()["max_bytes"]
    assert 0 < granted < free_bytes(data)  # not 2 GiB on a disk with 1 MB free
    u = api.get("/storage").json()
    assert u["reserved_bytes"] == granted and u["free_bytes"] <= u["disk_free_bytes"]
    assert _cut(serve, 3000, 2.0) > 0  # ~1.4 MB of rows: more than granted
    status = api.get(f"/sessions/{sid}/recording").json()
    assert "max_bytes" in status["stopped_reason"]
    stopped = api.delete(f"/sessions/{sid}/recording").json()
    assert stopped["rows_written"] > 0 and "error" not in stopped
    path = data / "recordings" / "granted.burrrec"
    rec = read_recording(path)
    assert rec.complete and len(rec.rows) == stopped["rows_written"]
    assert replay(path).reproduced
    assert api.delete("/recordings/granted").status_code == 200


def test_a_recording_the_disk_fills_up_under_keeps_the_rows_that_fit(served, api, data):
    serve, _ = served
    sid = serve.connection.session
    r = api.post(f"/sessions/{sid}/recording", json={"name": "filled"})
    assert r.status_code == 201, r.text
    # Something else takes the disk meanwhile: the room the recording holds is not its own
    # any more (only the budget keeps it; a disk is shared).
    fill(data, leave_bytes=100 << 10)
    ticks = _cut(serve, 600, 4.0)
    assert ticks > 0
    stopped = api.delete(f"/sessions/{sid}/recording").json()
    assert "the disk is full" in stopped["stopped_reason"], stopped
    assert 0 < stopped["rows_written"] < ticks
    assert "error" not in stopped  # summary.json was written, in the room held for it
    path = data / "recordings" / "filled.burrrec"
    assert (path / SUMMARY_NAME).is_file()
    rec = read_recording(path)
    assert rec.complete and len(rec.rows) == stopped["rows_written"]
    assert not [p.name for p in path.iterdir() if p.name.endswith(".part")]
    (data / FILLER).unlink()
    assert replay(path).reproduced
    assert api.delete("/recordings/filled").status_code == 200
    # The session streams on after all that.
    time.sleep(0.1)
    assert _cut(serve, 20, 5.0) > 0
