"""Recording a session's stream and replaying it offline (``burrforce replay``)."""

from __future__ import annotations

import csv
import json
import math
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from burrforce.proto.codec import decode_server_message
from burrforce.proto.messages import (
    FLAG_NO_CARVE,
    OK,
    STATUS_CUTTING,
    STATUS_FORBIDDEN,
    Pose,
    Reply,
)
from burrforce.server.bone import BoneEngine
from burrforce.server.bone.loaders import load_bone
from burrforce.server.bone.phantoms import TRABECULAR_LABEL, phantom
from burrforce.server.cli import main
from burrforce.server.hotloop import Session, SessionConfig
from burrforce.server.record import (
    FORMAT_NAME,
    REC_CARVE_RESET,
    ROW_DTYPE,
    Recorder,
    RecordingError,
    read_recording,
    replay,
    session_meta,
    start_recording,
)
from burrforce.server.record.format import ROW_STRUCT, chunk_name

T0_NS = 10**12
ALPHA_DEG = 60.0


def tilted(alpha_deg: float = ALPHA_DEG) -> tuple[float, float, float, float]:
    """Quaternion taking +z to the thesis's tool axis (−cos α, 0, sin α)."""
    beta = math.radians(alpha_deg - 90.0)
    return (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))


def make_session(name: str = "workpiece") -> Session:
    bone = phantom(name, 0.25)
    return Session(1, BoneEngine(bone.grid, bone.materials), SessionConfig())


class Driver:
    """Feeds a session poses at 1 kHz (client and server clocks), as the dispatcher would."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self.seq = 0
        self._due_s = 0.0

    def tick(self, position, *, rpm: float = 60_000.0, on: bool = True, flags: int = 0,
             orientation=None) -> Reply:
        # At 1 kHz in wall time too, as packets arrive: the recorder's writer thread gets the
        # time it has in a server. Unpaced, beside other work, it lost the GIL long enough for
        # every spare chunk (64 rows here, 4 096 in a server) to fill.
        wait_s = self._due_s - time.perf_counter()
        if wait_s > 0:
            time.sleep(wait_s)
        self._due_s = max(self._due_s, time.perf_counter() - 0.01) + 1e-3
        self.seq += 1
        t_us = self.seq * 1000
        now_ns = T0_NS + t_us * 1000
        pose = Pose(1, self.seq, t_us, tuple(position), orientation or tilted(), rpm, on,
                    None, flags)
        assert self.session.admit(pose.seq) == OK
        data, error = self.session.respond(pose, now_ns)
        assert error == OK
        reply = decode_server_message(data)
        assert isinstance(reply, Reply)
        return reply

    def groove(self, n: int, *, depth_mm: float = 0.5, feed_mm_s: float = 20.0,
               x0: float = 2.0, **kw) -> list[Reply]:
        """A straight groove along +x at α = 60°, n ticks."""
        start = self.seq
        flags = kw.pop("flags", 0)
        return [self.tick((x0 + feed_mm_s * (self.seq + 1 - start) * 1e-3, 0.0,
                           2.0 - depth_mm),
                          flags=flags, **kw)
                for _ in range(n)]


def varied_stream(driver: Driver) -> list[Reply]:
    """A groove with a no-carve stretch, a slow spindle, a spindle stop and a teleport."""
    replies = driver.groove(120)
    replies += driver.groove(30, x0=4.4, flags=FLAG_NO_CARVE)
    replies += driver.groove(20, x0=5.0, rpm=1000.0)
    replies += driver.groove(20, x0=5.4, on=False)
    # 6 mm in one millisecond: a teleport (the engine forgets where it last carved).
    replies += driver.groove(130, x0=12.0, depth_mm=0.8)
    return replies


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A 320-tick stream recorded in 64-row chunks (a partial last chunk)."""
    root = tmp_path_factory.mktemp("rec")
    session = make_session()
    recorder = start_recording(session, root / "groove", bone_name="workpiece", chunk_rows=64)
    assert session.recorder is recorder
    replies = varied_stream(Driver(session))
    status = recorder.close()
    return {"path": recorder.path, "session": session, "replies": replies, "status": status}


# -- recording --------------------------------------------------------------------------------
def test_row_layout_matches_the_struct_the_hot_path_packs():
    assert ROW_STRUCT.size == ROW_DTYPE.itemsize == 472
    assert all(ROW_DTYPE.fields[name][1] % 8 == 0 for name in ROW_DTYPE.names
               if ROW_DTYPE.fields[name][0].base.itemsize == 8)


def test_the_recording_holds_every_tick_as_the_session_answered(recorded):
    path, replies, session = recorded["path"], recorded["replies"], recorded["session"]
    assert path.name == "groove.burrrec"
    assert recorded["status"]["stopped_reason"] is None
    assert recorded["status"]["rows"] == recorded["status"]["rows_written"] == len(replies)
    assert recorded["status"]["chunks"] == math.ceil(len(replies) / 64)
    assert session.recorder is None  # close() detached it
    assert "forget_last_carve" not in vars(session.engine)
    rec = read_recording(path)
    assert rec.complete and rec.problems == []
    assert rec.chunks == math.ceil(len(replies) / 64)
    rows = rec.rows
    assert len(rows) == len(replies)
    np.testing.assert_array_equal(rows["seq"], [r.seq for r in replies])
    np.testing.assert_array_equal(rows["status"], [r.status for r in replies])
    np.testing.assert_array_equal(rows["force"], [r.force for r in replies])
    np.testing.assert_array_equal(rows["torque"], [r.torque for r in replies])
    np.testing.assert_array_equal(rows["removed_mm3"], [r.removed_mm3 for r in replies])
    np.testing.assert_array_equal(rows["bone_version"], [r.bone_version for r in replies])
    np.testing.assert_array_equal(rows["t_recv_ns"] // 1000, [r.t_recv_us for r in replies])
    assert np.isnan(rows["velocity"]).all()  # the client sent none
    assert rows["carve"][:120].all() and not rows["carve"][120:150].any()
    assert not rows["spindle_on"][170:190].any() and (rows["rpm"][170:190] == 0.0).all()
    assert (rows["pose_rpm"][150:170] == 1000.0).all()
    # The teleport made the engine forget its last carve: noted on that tick only.
    resets = np.flatnonzero(rows["rec_flags"] & REC_CARVE_RESET)
    assert 190 in resets.tolist()
    assert any(r.status & STATUS_CUTTING for r in replies)
    assert rows["bone_version"][-1] == session.engine.grid.version > 0


def test_meta_names_everything_a_replay_needs(recorded):
    meta = json.loads((recorded["path"] / "meta.json").read_text())
    engine = recorded["session"].engine
    assert meta["format"] == FORMAT_NAME and meta["format_version"] == 1
    assert meta["session_id"] == 1 and meta["frame"] == "si_mm"
    assert meta["params"]["us_n_mm2"] == engine.params.us_n_mm2
    assert meta["shaft"]["radius_mm"] == engine.shaft.radius_mm
    assert meta["materials"] == [{"label": 1, "name": "cortical", "us_n_mm2": 805.1,
                                  "k": 1.3, "forbidden": False}]
    assert meta["bone_name"] == "workpiece" and meta["bone_version"] == 0
    assert meta["snapshot"] == "start.bone.npz"
    assert meta["vibration"] is not None
    assert "T" in meta["start_time"]
    summary = json.loads((recorded["path"] / "summary.json").read_text())
    assert summary["rows"] == len(recorded["replies"]) and summary["dropped"] == 0
    # The snapshot is the bone before the first tick.
    start = load_bone(recorded["path"] / "start.bone.npz")
    assert start.grid.version == 0 and not start.grid.swept.any()


def test_chunks_are_plain_npy_files(recorded):
    rows = np.load(recorded["path"] / chunk_name(0))
    assert rows.dtype == ROW_DTYPE and len(rows) == 64
    last = np.load(recorded["path"] / chunk_name(4))
    assert len(last) == len(recorded["replies"]) - 4 * 64


# -- replay -----------------------------------------------------------------------------------
def test_replay_reproduces_every_tick_exactly(recorded):
    report = replay(recorded["path"])
    session, replies = recorded["session"], recorded["replies"]
    assert report.ticks == len(replies)
    assert report.max_deviation == {"out": 0.0, "shaft_out": 0.0, "force_N": 0.0,
                                    "torque": 0.0, "removed_mm3": 0.0, "bone_version": 0.0}
    assert report.mismatched_ticks == 0 and report.reproduced
    assert report.final_bone_version == session.engine.grid.version
    np.testing.assert_array_equal(report.force, [r.force for r in replies])
    np.testing.assert_array_equal(report.removed_mm3_tick, [r.removed_mm3 for r in replies])
    np.testing.assert_array_equal(report.status, [r.status for r in replies])
    assert report.removed_mm3_by_material == session.engine.removed_mm3_by_material()
    # The replayed bone is the live one, voxel for voxel.
    np.testing.assert_array_equal(report.bone.grid.swept, session.engine.grid.swept)
    assert report.cutting_ticks == sum(bool(r.status & STATUS_CUTTING) for r in replies)
    assert report.mean_force_N == report.recorded_mean_force_N > 0.0
    assert report.duration_s == pytest.approx((len(replies) - 1) * 1e-3)
    assert report.complete and report.notes == [] and report.forbidden_events == []


def test_replay_with_twice_the_cutting_energy_doubles_the_cutting_force(recorded):
    base = replay(recorded["path"])
    what_if = replay(recorded["path"], us_scale=2.0)
    assert what_if.overrides == {"us_scale": 2.0}
    assert not what_if.reproduced and what_if.max_deviation["force_N"] > 0.0
    cutting = (base.status & STATUS_CUTTING) != 0
    assert cutting.sum() > 100
    assert not base.shaft_out.any()  # the shaft stays clear: the whole force is cutting
    np.testing.assert_allclose(what_if.force[cutting], 2.0 * base.force[cutting],
                               rtol=1e-12, atol=1e-12)
    assert what_if.mean_force_N == pytest.approx(2.0 * base.mean_force_N, rel=1e-12)
    # Us does not change what the burr removes.
    np.testing.assert_array_equal(what_if.removed_mm3_tick, base.removed_mm3_tick)
    assert what_if.max_deviation["removed_mm3"] == 0.0


def test_replay_material_overrides(recorded):
    k0 = replay(recorded["path"], k=0.0)
    cutting = (k0.status & STATUS_CUTTING) != 0
    assert not np.array_equal(k0.force[cutting], replay(recorded["path"]).force[cutting])
    same = replay(recorded["path"], materials={"cortical": {"us_n_mm2": 805.1 * 2}})
    np.testing.assert_array_equal(same.force, replay(recorded["path"], us_scale=2.0).force)
    with pytest.raises(ValueError, match="no material 'bone'"):
        replay(recorded["path"], materials={"bone": {"k": 1.0}})
    with pytest.raises(ValueError, match="unknown fields"):
        replay(recorded["path"], materials={"cortical": {"density": 1.0}})
    with pytest.raises(ValueError, match="us_scale"):
        replay(recorded["path"], us_scale=-1.0)


def test_forbidden_contacts_are_replayed(tmp_path):
    """The layered block with its trabecular core made forbidden: cutting 2 mm deep through
    the 1.5 mm shell touches it."""
    session = make_session("layered")
    session.engine.materials.update(TRABECULAR_LABEL, forbidden=True)
    recorder = start_recording(session, tmp_path / "deep", chunk_rows=100)
    replies = Driver(session).groove(250, depth_mm=2.2)
    recorder.close()
    assert any(r.status & STATUS_FORBIDDEN for r in replies)
    report = replay(recorder.path)
    assert report.reproduced
    assert len(report.forbidden_events) == len(session.engine.events) >= 1
    assert report.forbidden_events[0]["material"] == "trabecular"
    assert set(report.removed_mm3_by_material) == {"cortical", "trabecular"}
    assert report.removed_mm3_by_material == session.engine.removed_mm3_by_material()


def test_a_recording_can_start_mid_stream(tmp_path):
    """Started after 100 ticks of carving: the snapshot holds the groove so far and the
    engine's carving state is restored, so the replay is still exact."""
    session = make_session()
    driver = Driver(session)
    driver.groove(100)
    recorder = start_recording(session, tmp_path / "late", chunk_rows=4096)
    driver.groove(150, x0=4.0)
    recorder.close()
    meta = read_recording(recorder.path).meta
    assert meta["bone_version"] > 0 and meta["carve_from_g"] is not None
    report = replay(recorder.path)
    assert report.ticks == 150 and report.reproduced
    np.testing.assert_array_equal(report.bone.grid.swept, session.engine.grid.swept)


# -- damage -----------------------------------------------------------------------------------
def test_a_truncated_last_chunk_keeps_its_whole_rows(recorded, tmp_path):
    copy = Path(shutil.copytree(recorded["path"], tmp_path / "torn.burrrec"))
    last = copy / chunk_name(4)
    data = last.read_bytes()
    last.write_bytes(data[:-(ROW_DTYPE.itemsize * 10 + 100)])  # 10 rows and a bit lost
    rec = read_recording(copy)
    n = len(recorded["replies"])
    assert len(rec.rows) == n - 11
    assert not rec.complete and len(rec.problems) == 1 and "torn" in rec.problems[0]
    report = replay(rec)
    assert report.ticks == n - 11 and report.reproduced and not report.complete


def test_a_damaged_middle_chunk_stops_the_stream_there(recorded, tmp_path):
    copy = Path(shutil.copytree(recorded["path"], tmp_path / "gap.burrrec"))
    (copy / chunk_name(1)).write_bytes(b"\x93NUMPY garbage")
    rec = read_recording(copy)
    assert len(rec.rows) == 64
    assert any("no readable header" in p for p in rec.problems)
    assert any("not read" in p for p in rec.problems)
    (copy / chunk_name(1)).unlink()
    rec = read_recording(copy)
    assert len(rec.rows) == 64 and any("missing" in p for p in rec.problems)


def test_a_chunk_left_half_written_by_a_crash(recorded, tmp_path):
    """A crash while a chunk was written leaves a ``.part`` file and no summary."""
    copy = Path(shutil.copytree(recorded["path"], tmp_path / "crash.burrrec"))
    (copy / "summary.json").unlink()
    data = (copy / chunk_name(4)).read_bytes()
    (copy / chunk_name(4)).unlink()
    (copy / (chunk_name(4) + ".part")).write_bytes(data[:len(data) // 2])
    rec = read_recording(copy)
    assert rec.summary is None and not rec.complete
    assert 4 * 64 < len(rec.rows) < len(recorded["replies"])
    assert any(".part" in p for p in rec.problems)
    assert replay(rec).reproduced


def test_unreadable_recordings_are_clear_errors(recorded, tmp_path):
    with pytest.raises(RecordingError, match="no such recording"):
        read_recording(tmp_path / "nothing.burrrec")
    (tmp_path / "empty.burrrec").mkdir()
    with pytest.raises(RecordingError, match=r"no meta\.json"):
        read_recording(tmp_path / "empty.burrrec")
    (tmp_path / "file").write_text("x")
    with pytest.raises(RecordingError, match="not a recording"):
        read_recording(tmp_path / "file")
    foreign = tmp_path / "foreign.burrrec"
    foreign.mkdir()
    (foreign / "meta.json").write_text('{"format": "something else"}')
    with pytest.raises(RecordingError, match="not a burrforce recording"):
        read_recording(foreign)
    (foreign / "meta.json").write_text("{not json")
    with pytest.raises(RecordingError, match="unreadable"):
        read_recording(foreign)
    copy = Path(shutil.copytree(recorded["path"], tmp_path / "other.burrrec"))
    np.save(copy / chunk_name(2), np.zeros(5, dtype=[("x", "<f8")]))
    with pytest.raises(RecordingError, match="not a chunk of this format"):
        read_recording(copy)
    copy = Path(shutil.copytree(recorded["path"], tmp_path / "nosnap.burrrec"))
    (copy / "start.bone.npz").unlink()
    with pytest.raises(RecordingError, match="snapshot"):
        replay(copy)


# -- limits -----------------------------------------------------------------------------------
def test_max_bytes_stops_recording_not_the_session(tmp_path):
    session = make_session()
    free = make_session()
    recorder = start_recording(session, tmp_path / "small", chunk_rows=32,
                               max_bytes=100 * ROW_DTYPE.itemsize + 4 * 200)
    replies = Driver(session).groove(300)
    unrecorded = Driver(free).groove(300)
    status = recorder.status()
    assert status["recording"] is False and "max_bytes" in status["stopped_reason"]
    assert status["rows"] == recorder.max_rows and 90 <= recorder.max_rows <= 100
    assert status["dropped"] == 300 - recorder.max_rows
    # The session answered exactly as one that records nothing.
    assert [(r.force, r.status, r.removed_mm3) for r in replies] \
        == [(r.force, r.status, r.removed_mm3) for r in unrecorded]
    status = recorder.close()
    assert status["bytes"] <= recorder.max_bytes
    assert sum(f.stat().st_size for f in recorder.path.glob("chunk-*")) == status["bytes"]
    rec = read_recording(recorder.path)
    assert len(rec.rows) == recorder.max_rows and rec.complete
    assert "max_bytes" in rec.stopped_reason
    assert replay(rec).reproduced


def test_a_stalled_writer_stops_recording_without_blocking(tmp_path):
    session = make_session()
    recorder = start_recording(session, tmp_path / "stall", chunk_rows=8)
    gate = threading.Event()
    write = recorder._write_chunk

    def slow_write(*args):
        gate.wait(10.0)
        write(*args)

    recorder._write_chunk = slow_write
    t0 = time.perf_counter()
    Driver(session).groove(100)
    assert time.perf_counter() - t0 < 5.0
    status = recorder.status()
    assert "fell behind" in status["stopped_reason"]
    assert status["rows"] == 8 * 4 and status["dropped"] == 100 - 8 * 4
    gate.set()
    status = recorder.close()
    assert status["rows_written"] == 32 and status["chunks"] == 4
    assert replay(recorder.path).reproduced


def test_a_failing_disk_stops_recording_and_keeps_what_was_written(tmp_path):
    session = make_session()
    recorder = start_recording(session, tmp_path / "full", chunk_rows=16)
    write = recorder._write_chunk
    calls = []

    def failing_write(index, mv, n):
        calls.append(index)
        if index >= 2:
            raise OSError(28, "No space left on device")
        write(index, mv, n)

    recorder._write_chunk = failing_write
    driver = Driver(session)
    driver.groove(40)
    deadline = time.monotonic() + 10.0
    while recorder.status()["recording"] and time.monotonic() < deadline:
        time.sleep(0.01)
        driver.groove(1, x0=3.0)
    status = recorder.close()
    assert "No space left" in status["stopped_reason"]
    assert status["chunks"] == 2 and status["rows_written"] == 32
    rec = read_recording(recorder.path)
    assert len(rec.rows) == 32 and "No space left" in rec.stopped_reason
    assert replay(rec).reproduced


def test_changing_materials_mid_recording_stops_it(tmp_path):
    session = make_session()
    recorder = start_recording(session, tmp_path / "change")
    driver = Driver(session)
    driver.groove(50)
    session.engine.materials.update(1, us_n_mm2=900.0)
    driver.groove(10, x0=3.0)
    status = recorder.close()
    assert status["rows"] == 50 and status["dropped"] == 10
    assert "changed" in status["stopped_reason"]
    assert replay(recorder.path).reproduced


def test_create_refuses_to_overwrite_and_checks_its_arguments(recorded, tmp_path):
    meta = session_meta(make_session())
    with pytest.raises(ValueError, match="already holds a recording"):
        Recorder.create(recorded["path"], meta, None)
    with pytest.raises(ValueError, match="already exists"):
        start_recording(make_session(), recorded["path"])
    with pytest.raises(ValueError, match="chunk_rows"):
        Recorder.create(tmp_path / "a", meta, None, chunk_rows=0)
    with pytest.raises(ValueError, match="lacks"):
        Recorder.create(tmp_path / "b", {"frame": "si_mm"}, None)
    # Without a snapshot it records, and cannot be replayed.
    session = make_session()
    recorder = Recorder.create(tmp_path / "c", meta, None)
    recorder.attach(session)
    with pytest.raises(ValueError, match="already being recorded"):
        Recorder.create(tmp_path / "d", meta, None).attach(session)
    Driver(session).groove(5)
    assert recorder.close()["rows"] == 5
    assert read_recording(recorder.path).snapshot is None
    with pytest.raises(RecordingError, match="no start snapshot"):
        replay(recorder.path)


# -- the command ------------------------------------------------------------------------------
def test_cli_replay_summary_json_csv_and_bone(recorded, tmp_path, capsys):
    path = recorded["path"]
    assert main(["replay", str(path)]) == 0
    text = capsys.readouterr().out
    assert "reproduced exactly" in text and f"{len(recorded['replies'])} ticks" in text

    csv_path = tmp_path / "forces.csv"
    bone_path = tmp_path / "end.bone.npz"
    assert main(["replay", str(path), "--json", "--csv", str(csv_path),
                 "--bone-out", str(bone_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["reproduced"] is True and report["ticks"] == len(recorded["replies"])
    assert report["max_deviation"]["force_N"] == 0.0
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(recorded["replies"])
    assert [float(r["fx_N"]) for r in rows] == [r.force[0] for r in recorded["replies"]]
    end = load_bone(bone_path)
    np.testing.assert_array_equal(end.grid.swept, recorded["session"].engine.grid.swept)
    assert end.grid.version == recorded["session"].engine.grid.version

    assert main(["replay", str(path), "--json", "--us-scale", "2", "--k", "1.3"]) == 0
    what_if = json.loads(capsys.readouterr().out)
    assert what_if["overrides"] == {"us_scale": 2.0, "k": 1.3}
    assert what_if["mean_force_N"] == pytest.approx(2.0 * report["mean_force_N"], rel=1e-9)


def test_cli_replay_errors(tmp_path, capsys):
    assert main(["replay", str(tmp_path / "missing.burrrec")]) == 2
    assert "burrforce replay: error:" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["replay", str(tmp_path), "--us-scale", "-1"])
