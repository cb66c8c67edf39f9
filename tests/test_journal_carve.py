"""The carve log: records of carved bricks that give the carved bone back after a crash."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.api.journal_carve import CarveLog, apply_log, read_log
from burrforce.server.bone import BoneEngine, ShaftParams, phantom
from burrforce.server.model.params import CuttingParams


def _groove(engine: BoneEngine, start_mm: float, n: int) -> None:
    """A cut along +x at 5 mm/s, 0.6 mm under the workpiece's top (the engine takes grid
    coordinates)."""
    grid = engine.grid
    axis = np.array([0.0, 0.0, 1.0])
    feed = np.array([5.0, 0.0, 0.0])
    for i in range(n):
        centre = grid.to_grid_point(np.array([start_mm + 0.005 * i, 0.0, -0.6]))
        engine.step_raw(centre, axis, feed, 60000.0, True)
    assert grid.version > 0


@pytest.fixture()
def carved():
    bone = phantom("workpiece", 0.2)
    engine = BoneEngine(bone.grid, bone.materials, CuttingParams(), ShaftParams(length_mm=0.0))
    return bone, engine


def test_replaying_the_log_gives_the_carved_bone_back(tmp_path, carved):
    bone, engine = carved
    log = CarveLog(tmp_path / "carve.log")
    for start in (3.0, 6.0, 9.0):  # three passes of the journal, cutting between them
        _groove(engine, start, 300)
        assert log.append(bone.grid.swept, bone.grid.brick_version) > 0
    # The last tick's bricks once more (a tick might have been writing them), then nothing.
    log.append(bone.grid.swept, bone.grid.brick_version)
    assert log.append(bone.grid.swept, bone.grid.brick_version) == 0
    fresh = phantom("workpiece", 0.2)
    index, version, swept = read_log(tmp_path / "carve.log")
    assert apply_log(fresh.grid, index, version, swept) == len(index)
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)
    assert np.array_equal(fresh.grid.brick_version, bone.grid.brick_version)
    assert np.array_equal(fresh.grid.brick_bone, bone.grid.brick_bone)
    assert fresh.grid.version == bone.grid.version


def test_a_record_cut_short_ends_the_log_and_keeps_what_came_before(tmp_path, carved):
    bone, engine = carved
    path = tmp_path / "carve.log"
    log = CarveLog(path)
    _groove(engine, 3.0, 200)
    log.append(bone.grid.swept, bone.grid.brick_version)
    first = path.stat().st_size
    kept = bone.grid.swept.copy()
    _groove(engine, 6.0, 200)
    log.append(bone.grid.swept, bone.grid.brick_version)
    data = path.read_bytes()
    for cut in (first + 3, first + 20, len(data) - 1):  # a crash in the second write
        path.write_bytes(data[:cut])
        fresh = phantom("workpiece", 0.2)
        apply_log(fresh.grid, *read_log(path))
        assert np.array_equal(fresh.grid.swept, kept)
    # A server that goes on after a torn record (resumed, or a write that failed) cuts it
    # off first: what it appends next is read back.
    path.write_bytes(data[:first + 20])
    log = CarveLog(path)
    _groove(engine, 12.0, 200)
    log.append(bone.grid.swept, bone.grid.brick_version)
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)
    data = path.read_bytes()
    damaged = bytearray(data)
    damaged[-5] ^= 0xFF  # a flipped bit in the second record's payload: its CRC fails
    path.write_bytes(bytes(damaged))
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    assert np.array_equal(fresh.grid.swept, kept)


def test_compaction_keeps_the_latest_record_of_each_brick(tmp_path, carved, monkeypatch):
    bone, engine = carved
    monkeypatch.setattr(CarveLog, "COMPACT_MIN_BYTES", 1)
    path = tmp_path / "carve.log"
    log = CarveLog(path)
    sizes = []
    for k in range(12):  # the burr goes back and forth over the same bricks
        _groove(engine, 4.0 + (k % 2) * 0.01, 100)
        log.append(bone.grid.swept, bone.grid.brick_version)
        sizes.append(path.stat().st_size)
    index, _, _ = read_log(path)
    one_record = 16 + len(index) * (12 + 8 + 512)
    assert path.stat().st_size <= CarveLog.COMPACT_RATIO * one_record
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)


def test_a_log_for_another_bone_is_refused(tmp_path, carved):
    bone, engine = carved
    log = CarveLog(tmp_path / "carve.log")
    _groove(engine, 20.0, 300)
    log.append(bone.grid.swept, bone.grid.brick_version)
    small = phantom("workpiece", 1.0)
    with pytest.raises(ValueError, match="outside this bone"):
        apply_log(small.grid, *read_log(tmp_path / "carve.log"))


@settings(max_examples=examples(40), deadline=None)
@given(st.binary(max_size=3000))
def test_any_bytes_read_as_a_log_never_raise(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("fuzz") / "carve.log"
    path.write_bytes(data)
    index, version, swept = read_log(path)
    assert len(index) == len(version) == len(swept)
