"""A journal that never lies (issue 44), against the real supervisor and the real ``serve``:
the removed volume and forbidden contacts survive a hot-loop kill and a serve restart equal to
the true totals; a damaged journal never stops ``serve`` nor loses the key, and what it lost is
reported exactly (mm³) with every damaged file kept; a journal that cannot be written shows as
degraded until it can, and a kill -9 in that window says what it cost."""

from __future__ import annotations

import errno
import io
import os
import shutil
import signal
import struct
import subprocess
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from waiting import wait_until

from burrforce.client.udp import BurrClient, ServerGone
from burrforce.server.api import journal_format
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.journal_state import read_state
from burrforce.server.api.models import Parameters
from burrforce.server.api.stack import ServerStack
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.bone.bricks import BRICK
from burrforce.server.bone.phantoms import TRABECULAR_LABEL

TOKEN = "journal-recovery-token-0123456789"
BONE = ("--bone", "phantom:layered", "--voxel-mm", "0.25")
VOXEL_MM3 = 0.25 ** 3
# The burr (2 mm) 1 mm into the 1.5 mm shell, or 3 mm down: into the (forbidden) core.
SHALLOW_Z, DEEP_Z = 1.0, -1.0


def _groove(client: BurrClient, y_mm: float, z_mm: float, n: int = 200) -> None:
    for i in range(n):
        try:
            client.exchange((2.0 + 0.01 * i, y_mm, z_mm), rpm=60000.0, timeout_s=0.5)
        except (TimeoutError, ServerGone):
            pass
        time.sleep(0.0005)


def _cut(client: BurrClient, y_mm: float) -> None:
    """Into the core and out again: removal and one forbidden contact at least."""
    _groove(client, y_mm, DEEP_Z)
    _groove(client, y_mm + 0.01, SHALLOW_Z, 20)


def _total(state: dict) -> float:
    return sum(state["removed_mm3"].values())


def _events(state: dict) -> list[tuple]:
    return [(e["time_s"], tuple(e["position_mm"]), e["label"]) for e in state["events"]]


# -- counters across a hot-loop kill and a serve restart --------------------------------------
def test_counters_survive_a_hot_loop_kill_and_a_serve_restart_equal_to_the_bone(tmp_path):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path)
    with ServerStack(config, TOKEN) as stack:
        source = stack.plane.resolve("phantom:layered", None, 0.25)
        session = stack.add_session(source, Parameters(), session_id=3)
        stack.plane.set_material(3, TRABECULAR_LABEL, None, {"forbidden": True})
        with BurrClient(*stack.udp_address, 3, session.key_hex) as client:
            _cut(client, 0.0)
            before = stack.plane.session_state(3, 10_000)
            assert _total(before) > 0 and before["forbidden_events"] >= 1
            os.kill(stack.hot.pid, signal.SIGKILL)
            assert wait_until(lambda: stack.supervisor.restarts
                              and stack.supervisor.restarts[-1].recovery_s is not None)
            after = stack.plane.session_state(3, 10_000)
            assert after["removed_mm3"] == before["removed_mm3"]  # not from zero
            assert after["forbidden_events"] == before["forbidden_events"]
            assert _events(after) == _events(before)
            _cut(client, 4.0)
        final = stack.plane.session_state(3, 10_000)
        assert final["forbidden_events"] > before["forbidden_events"]
        assert _events(final)[:len(_events(before))] == _events(before)
        # The true total: what the bone lost, Σ density × swept (it was loaded uncarved).
        reader = session.reader
        units = np.bincount(reader.labels.ravel(), minlength=256, weights=(
            reader.density.astype(np.float64) * reader.swept).ravel())
        assert _total(final) == pytest.approx(units.sum() * VOXEL_MM3 / 255 ** 2, rel=1e-12)
        line = (f'burrforce_forbidden_contacts_total{{session="3"}} '
                f'{float(final["forbidden_events"])}')
        assert wait_until(lambda: line in httpx.get(  # the statistics' next poll
            stack.url + "/metrics", headers={"Authorization": f"Bearer {TOKEN}"}).text)
    with ServerStack(config, TOKEN) as stack:  # serve stopped and started again
        assert stack.resumed == [3]
        resumed = stack.plane.session_state(3, 10_000)
        assert resumed["removed_mm3"] == final["removed_mm3"]
        assert resumed["forbidden_events"] == final["forbidden_events"]
        assert _events(resumed) == _events(final)
        view = httpx.get(stack.url + "/v1/sessions/3",
                         headers={"Authorization": f"Bearer {TOKEN}"}).json()
        assert view["journal"]["state"] == "ok" and view["journal"]["recovery"] is None


# -- a damaged journal, against the real serve -------------------------------------------------
def _api(c) -> httpx.Client:
    return httpx.Client(base_url=c.http_url, timeout=60.0,
                        headers={"Authorization": f"Bearer {c.token}"})


def _swept(api: httpx.Client, sid: int, what: str = "swept") -> np.ndarray:
    r = api.get(f"/v1/sessions/{sid}/export/volume", params={"format": "npy", "what": what})
    r.raise_for_status()
    return np.load(io.BytesIO(r.content))


def _bricks_back_to_the_source(before: np.ndarray, after: np.ndarray) -> int:
    """Bricks (``bone.bricks.BRICK``³ voxels) that had swept voxels and have none now."""
    pad = [(0, -n % BRICK) for n in before.shape]

    def per_brick(swept: np.ndarray) -> np.ndarray:
        a = np.pad(swept, pad)
        nx, ny, nz = (n // BRICK for n in a.shape)
        return a.reshape(nx, BRICK, ny, BRICK, nz, BRICK).any(axis=(1, 3, 5))

    return int((per_brick(before) & ~per_brick(after)).sum())


def _folder(data: Path, sid: int) -> Path:
    return data / "journal" / "sessions" / str(sid)


def _caught_up(folder: Path, version: int) -> bool:
    state = read_state(folder / "state.bin")
    return state is not None and state.bone_version == version and not state.unlogged_bricks


@pytest.fixture(scope="module")
def journaled(tmp_path_factory):
    """A serve that cut four grooves (four passes of the journal, contacts among them), then
    was killed with SIGKILL once its journal held it all."""
    folder = tmp_path_factory.mktemp("journaled")
    first = spawn_serve(folder, *BONE)
    try:
        c = first.connection
        with _api(c) as api:
            api.patch(f"/v1/sessions/{c.session}/materials/{TRABECULAR_LABEL}",
                      json={"forbidden": True}).raise_for_status()
            with BurrClient(c.host, c.udp_port, c.session, c.key_hex) as client:
                for y in (-6.0, -2.0, 2.0, 6.0):
                    _cut(client, y)
                    time.sleep(1.2)  # a pass of the journal between grooves
            state = api.get(f"/v1/sessions/{c.session}/state",
                            params={"max_events": 10_000}).json()
            swept = _swept(api, c.session)
            density = _swept(api, c.session, "density")
        assert wait_until(lambda: _caught_up(_folder(folder / "data", c.session),
                                             state["bone_version"]))
    finally:
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(30)
    return {"folder": folder, "conn": c, "state": state, "swept": swept, "density": density}


def _bricks_records(data: bytes):
    """(payload offset, length, brick index (n, 3), swept (n, 8, 8, 8)) of every bricks record
    of a format-2 log, in file order."""
    at, found = journal_format.FILE_HEAD_BYTES, []
    while at + journal_format.RECORD_HEAD_BYTES <= len(data):
        kind, n, length, _crc = struct.unpack_from("<4sIII", data, at)
        start = at + journal_format.RECORD_HEAD_BYTES
        if kind == journal_format.BRICKS:
            index = np.frombuffer(data, "<i4", 3 * n, start).reshape(n, 3)
            swept = np.frombuffer(data, np.uint8, n * BRICK ** 3,
                                  start + 20 * n).reshape(n, BRICK, BRICK, BRICK)
            found.append((start, length, index, swept))
        at = start + length
    return found


def _decisive_bricks_payload(data: bytes, density: np.ndarray) -> tuple[int, int]:
    """Where the payload of a bricks record starts, and its length, such that damaging it
    loses carving: the last record that is the newest of some brick whose bone it carved
    (density > 0) beyond that brick's previous record. Damage to any other record may lose
    nothing: a later record holds the same bricks again, or its bricks hold no carving of
    bone that their previous records lacked (seen in 1 run of 2 here when the last record
    was the target)."""
    records = _bricks_records(data)
    last_of = {}
    for r, (_, _, index, _) in enumerate(records):
        for b in map(tuple, index):
            last_of[b] = r
    for r in range(len(records) - 1, -1, -1):
        start, length, index, swept = records[r]
        for i, b in enumerate(map(tuple, index)):
            if last_of[b] != r:
                continue
            before = np.zeros((BRICK,) * 3, np.uint8)
            for _, _, index_e, swept_e in records[:r]:  # the brick's previous record
                hit = np.flatnonzero((index_e == b).all(axis=1))
                if hit.size:
                    before = swept_e[hit[-1]]
            lo = np.asarray(b) * BRICK
            bone = np.zeros((BRICK,) * 3, bool)
            part = density[lo[0]:lo[0] + BRICK, lo[1]:lo[1] + BRICK, lo[2]:lo[2] + BRICK] > 0
            bone[:part.shape[0], :part.shape[1], :part.shape[2]] = part
            if (swept[i][bone] != before[bone]).any():
                return start, length
    raise AssertionError("no bricks record whose damage would lose carving")


def _flip16(path: Path, density: np.ndarray) -> None:
    data = bytearray(path.read_bytes())
    start, length = _decisive_bricks_payload(bytes(data), density)
    for k in range(16):
        data[start + k * length // 16] ^= 0xFF
    path.write_bytes(bytes(data))


def _random4k(path: Path, density: np.ndarray) -> None:
    data = bytearray(path.read_bytes())
    at, _ = _decisive_bricks_payload(bytes(data), density)
    data[at:at + 4096] = np.random.default_rng(44).bytes(4096)
    path.write_bytes(bytes(data))


def _empty(path: Path, density: np.ndarray) -> None:
    path.write_bytes(b"")


DAMAGE = {"none": None, "16 flipped bytes": _flip16, "4 KB of random bytes": _random4k,
          "an empty file": _empty}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_carve_log_resumes_with_its_key_and_says_exactly_what_it_lost(
        journaled, tmp_path, damage):
    folder = tmp_path / "run"
    shutil.copytree(journaled["folder"], folder, symlinks=True)
    c, before = journaled["conn"], journaled["state"]
    journal = _folder(folder / "data", c.session)
    log = journal / "carve.log"
    if DAMAGE[damage] is not None:
        DAMAGE[damage](log, journaled["density"])
    damaged = log.read_bytes()
    names = {p.name for p in journal.iterdir()}
    second = spawn_serve(folder, *BONE)
    try:
        c2 = second.connection
        assert (c2.session, c2.key_hex) == (c.session, c.key_hex)  # the key is kept
        with _api(c2) as api:
            view = api.get(f"/v1/sessions/{c2.session}").json()
            health = httpx.get(c2.http_url + "/v1/health").json()
            state = api.get(f"/v1/sessions/{c2.session}/state",
                            params={"max_events": 10_000}).json()
            report = api.get(f"/v1/sessions/{c2.session}/report")
            swept = _swept(api, c2.session)
        # What the bone lost, from the voxels themselves.
        lost = float((journaled["density"].astype(np.float64)
                      * (journaled["swept"].astype(np.float64) - swept)).sum())
        lost_mm3 = lost * VOXEL_MM3 / 255 ** 2
        assert _total(state) == pytest.approx(_total(before) - lost_mm3, abs=1e-9)
        recovery = view["journal"]["recovery"]
        if damage == "none":
            assert lost == 0 and recovery is None and health["journal"]["recovered"] == []
            assert "carving and key as they were" in second.banner
            assert state["removed_mm3"] == before["removed_mm3"]
            assert state["forbidden_events"] == before["forbidden_events"]
            assert _events(state) == _events(before)
            return
        assert lost_mm3 > 0
        assert recovery["removed_mm3"] == pytest.approx(lost_mm3, abs=1e-9)
        # Bricks none of whose records survived are back to the phantom's unswept bone;
        # a brick whose latest record was lost but an older one survived holds that older
        # state: its loss is in removed_mm3, and it is not one of the bricks lost.
        assert recovery["bricks"] == _bricks_back_to_the_source(journaled["swept"], swept)
        assert recovery["measured"] is True
        assert f"{lost_mm3:.3f} mm³" in second.banner
        assert "carving and key as they were" not in second.banner
        assert health["status"] == "ok" and health["journal"]["state"] == "ok"
        assert [r["session"] for r in health["journal"]["recovered"]] == [c.session]
        assert health["journal"]["recovered"][0]["removed_mm3"] == recovery["removed_mm3"]
        assert any(recovery["summary"] in note for note in report.json()["notes"])
        # Nothing deleted: the damaged log kept, byte for byte, beside the new one.
        kept = [folder / "data" / p for p in recovery["kept"]]
        assert any(p.name.startswith("carve.log.damaged-") and p.read_bytes() == damaged
                   for p in kept)
        assert names <= {p.name for p in journal.iterdir()}
    finally:
        code, out = second.stop()
    assert code == 0, out


@pytest.mark.parametrize("record_format", [1, 2])
def test_an_invalid_key_in_session_json_is_quarantined_and_serve_starts(
        journaled, tmp_path, record_format):
    import json

    folder = tmp_path / "run"
    shutil.copytree(journaled["folder"], folder, symlinks=True)
    c = journaled["conn"]
    journal = _folder(folder / "data", c.session)
    record = json.loads((journal / "session.json").read_text())
    record["key_hex"] = "zz" + record["key_hex"][2:]
    if record_format == 1:  # as the previous release wrote it: no checksum to fail first
        record["format_version"] = 1
        record.pop("checksum")
    (journal / "session.json").write_text(json.dumps(record))
    files = {p.name: p.read_bytes() for p in journal.iterdir()}
    second = spawn_serve(folder, *BONE)  # it starts: before, it exited with status 2
    try:
        assert "could not be resumed" in second.banner
        health = httpx.get(second.connection.http_url + "/v1/health").json()
        kept = health["journal"]["quarantined"]
        assert len(kept) == 1 and kept[0]["session"] == str(c.session)
        reason = "invalid key" if record_format == 1 else "checksum"
        assert reason in kept[0]["reason"]
        aside = folder / "data" / kept[0]["folder"]
        assert aside.name.startswith(f"{c.session}.failed-")
        # Every file kept as it was (the damaged key with them), and the reason beside them.
        assert {p.name: p.read_bytes() for p in aside.iterdir() if p.name != "WHY.txt"} \
            == files
        assert (aside / "WHY.txt").exists()
    finally:
        code, out = second.stop()
    assert code == 0, out


# -- a journal that cannot be written ----------------------------------------------------------
@pytest.fixture()
def small_disk(tmp_path):
    """A 24 MB tmpfs: the data directory's disk, filled on demand."""
    mount = tmp_path / "disk"
    mount.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root (CI runs as root)")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=24m", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(disk: Path) -> Path:
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        for chunk in (1 << 20, 4096, 1):
            try:
                while True:
                    os.write(fd, b"\0" * chunk)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC
    finally:
        os.close(fd)
    return filler


def _journal_state(c) -> tuple[dict, dict]:
    health = httpx.get(c.http_url + "/v1/health").json()
    with _api(c) as api:
        view = api.get(f"/v1/sessions/{c.session}").json()
    return health, view


def test_a_journal_that_cannot_be_written_is_degraded_until_it_can_and_a_kill_says_its_cost(
        small_disk):
    first = spawn_serve(small_disk, *BONE)
    c = first.connection
    journal = _folder(small_disk / "data", c.session)
    try:
        with BurrClient(c.host, c.udp_port, c.session, c.key_hex) as client, _api(c) as api:
            _cut(client, -6.0)
            version = api.get(f"/v1/sessions/{c.session}/state").json()["bone_version"]
            assert wait_until(lambda: _caught_up(journal, version))
            filler = _fill(small_disk)
            _cut(client, -2.0)
            assert wait_until(lambda: _journal_state(c)[0]["status"] == "degraded")
            health, view = _journal_state(c)
            assert health["journal"]["degraded_sessions"] == [c.session]
            assert "No space left" in health["journal"]["error"]
            assert view["journal"]["state"] == "degraded" and view["journal"]["failing_since"]
            metrics = api.get("/metrics").text
            assert "burrforce_journal_up 0.0" in metrics
            assert f'burrforce_journal_degraded{{session="{c.session}"}} 1.0' in metrics
            notes = api.get(f"/v1/sessions/{c.session}/report").json()["notes"]
            assert any("cannot be written" in n for n in notes)
            filler.unlink()  # room again: written, and healthy, at the next pass
            assert wait_until(lambda: _journal_state(c)[0]["status"] == "ok")
            assert _journal_state(c)[1]["journal"]["state"] == "ok"
            assert "burrforce_journal_up 1.0" in api.get("/metrics").text
            _fill(small_disk)
            _cut(client, 2.0)
            assert wait_until(lambda: _journal_state(c)[0]["status"] == "degraded")
            before = api.get(f"/v1/sessions/{c.session}/state").json()
            # The state file, written in place, keeps up while the log cannot.
            assert wait_until(lambda: (read_state(journal / "state.bin").bone_version
                                       == before["bone_version"]))
    finally:
        first.proc.send_signal(signal.SIGKILL)
        first.proc.wait(30)
    (small_disk / "filler").unlink()
    second = spawn_serve(small_disk, *BONE)
    try:
        c2 = second.connection
        assert c2.key_hex == c.key_hex
        with _api(c2) as api:
            after = api.get(f"/v1/sessions/{c2.session}/state").json()
            recovery = api.get(f"/v1/sessions/{c2.session}").json()["journal"]["recovery"]
        lost_mm3 = _total(before) - _total(after)
        assert lost_mm3 > 0  # the carving since the disk filled: not journaled
        assert recovery["removed_mm3"] == pytest.approx(lost_mm3, abs=1e-9)
        assert recovery["versions"] == before["bone_version"] - after["bone_version"] > 0
        assert any("could not be written" in cause for cause in recovery["causes"])
        assert "could not be written" in second.banner
    finally:
        code, out = second.stop()
    assert code == 0, out


def test_a_journal_of_the_previous_release_resumes_and_is_migrated(journaled, tmp_path):
    """Format 1, as releases before this one wrote it: session.json without a checksum or a
    log id, a carve log of brick records with payload-only CRCs and no header, no state."""
    import json
    import struct
    import zlib

    from burrforce.server.api.journal_carve import read_carving

    folder = tmp_path / "run"
    shutil.copytree(journaled["folder"], folder, symlinks=True)
    c, before = journaled["conn"], journaled["state"]
    journal = _folder(folder / "data", c.session)
    record = json.loads((journal / "session.json").read_text())
    for key in ("checksum", "carve_log"):
        record.pop(key)
    record["format_version"] = 1
    (journal / "session.json").write_text(json.dumps(record))
    content = read_carving(journal / "carve.log")
    payload = (content.index.astype("<i4").tobytes() + content.version.astype("<i8").tobytes()
               + content.swept.tobytes())
    (journal / "carve.log").write_bytes(struct.pack(
        "<4sIII", b"BFCR", len(content.index), len(payload), zlib.crc32(payload)) + payload)
    (journal / "state.bin").unlink()
    second = spawn_serve(folder, *BONE)
    try:
        c2 = second.connection
        assert c2.key_hex == c.key_hex and "carving and key as they were" in second.banner
        with _api(c2) as api:
            # Every bone voxel as it was (air a burr passed is marked in bricks the journal
            # writes only once they lose bone: not carving).
            bone = journaled["density"] > 0
            assert np.array_equal(_swept(api, c2.session)[bone], journaled["swept"][bone])
            state = api.get(f"/v1/sessions/{c2.session}/state").json()
            assert state["removed_mm3"] == before["removed_mm3"]
            assert state["forbidden_events"] == 0  # format 1 kept none
            assert api.get(f"/v1/sessions/{c2.session}").json()["journal"]["recovery"] is None
        # Migrated: format 2 files, the same carving.
        assert json.loads((journal / "session.json").read_text())["format_version"] == 2
        migrated = read_carving(journal / "carve.log")
        assert migrated.scan.version == 2 and len(migrated.index) == len(content.index)
        assert read_state(journal / "state.bin") is not None
    finally:
        code, out = second.stop()
    assert code == 0, out


def test_journal_files_removed_while_serving_are_written_again_whole(tmp_path):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path)
    with ServerStack(config, TOKEN) as stack:
        source = stack.plane.resolve("phantom:workpiece", None, 0.5)
        session = stack.add_session(source, Parameters(), session_id=2)
        with BurrClient(*stack.udp_address, 2, session.key_hex) as client:
            for i in range(200):
                try:
                    client.exchange((3.0 + 0.01 * i, 0.0, -0.6), rpm=60000.0, timeout_s=0.5)
                except (TimeoutError, ServerGone):
                    pass
        stack.journal.write()
        journal = _folder(tmp_path, 2)
        shutil.rmtree(journal)
        stack.journal.write()
        assert session.journal.state == "ok"
        state = read_state(journal / "state.bin")
        assert state.bone_version == session.reader.version and not state.unlogged_bricks
        bone = session.reader.density > 0
        swept = session.reader.swept[bone].copy()
    with ServerStack(config, TOKEN) as stack:
        assert stack.resumed == [2]
        resumed = stack.plane.sessions[2]
        assert resumed.journal.recovery is None
        assert np.array_equal(resumed.reader.swept[bone], swept)
