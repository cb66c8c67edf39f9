"""The carve log: records of carved bricks that give the carved bone back after a crash."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.api.journal_carve import (
    BRICK_BYTES,
    RECORD_BRICKS,
    CarveLog,
    apply_log,
    read_carving,
    read_log,
)
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


def _replayed(path) -> np.ndarray:
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    return fresh.grid.swept


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
    records = len(read_carving(path).scan.records)
    for cut in (first + 3, first + 20):  # a crash in the second write's first record
        path.write_bytes(data[:cut])
        assert np.array_equal(_replayed(path), kept)
    # A crash in its last record: the records before it, whole bricks each, are kept.
    path.write_bytes(data[:-1])
    torn = read_carving(path).scan
    assert torn.tail > 0 and not torn.damaged and len(torn.records) == records - 1
    # A server that goes on after a torn record (resumed, or a write that failed) cuts it
    # off first: what it appends next is read back.
    path.write_bytes(data[:first + 20])
    log = CarveLog(path)
    _groove(engine, 12.0, 200)
    log.append(bone.grid.swept, bone.grid.brick_version)
    assert np.array_equal(_replayed(path), bone.grid.swept)
    data = path.read_bytes()
    last = read_carving(path).scan.records[-1]
    damaged = bytearray(data)
    damaged[-5] ^= 0xFF  # a flipped bit in the last record's payload: its CRC fails
    path.write_bytes(bytes(damaged))
    without_last = data[:len(data) - 16 - len(last[2])]
    (tmp_path / "expected.log").write_bytes(without_last)
    assert np.array_equal(_replayed(path), _replayed(tmp_path / "expected.log"))
    assert not np.array_equal(_replayed(path), bone.grid.swept)


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


# -- format 2: a header, CRCs over header and payload, damage skipped, contacts -------------
def _v1_record(index: np.ndarray, version: np.ndarray, swept: np.ndarray) -> bytes:
    """A record as releases before format 2 wrote it (no file header, CRC of the payload)."""
    import struct
    import zlib

    payload = (np.ascontiguousarray(index, dtype="<i4").tobytes()
               + np.ascontiguousarray(version, dtype="<i8").tobytes()
               + np.ascontiguousarray(swept, dtype=np.uint8).tobytes())
    return struct.pack("<4sIII", b"BFCR", len(index), len(payload),
                       zlib.crc32(payload)) + payload


def _records(log_path, bone, engine, grooves):
    """Append one record per groove; returns the file's size after each."""
    log = CarveLog(log_path, log_id=77)
    sizes = []
    for start in grooves:
        _groove(engine, start, 150)
        log.append(bone.grid.swept, bone.grid.brick_version)
        sizes.append(log_path.stat().st_size)
    return sizes


def test_a_format_1_log_reads_as_before_and_is_taken_up(tmp_path, carved):
    bone, engine = carved
    path = tmp_path / "carve.log"
    _groove(engine, 3.0, 200)
    index = np.argwhere(bone.grid.brick_version > 0)
    version = bone.grid.brick_version[tuple(index.T)]
    from burrforce.server.bone.shared import brick_blocks

    path.write_bytes(_v1_record(index, version, brick_blocks(bone.grid.swept, index)))
    content = read_carving(path)
    assert content.scan.version == 1 and not content.scan.damaged
    assert not content.scan.header_damaged and content.scan.log_id is None
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, content.index, content.version, content.swept)
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)
    # A format-2 writer taking it up appends records the reader reads with it.
    log = CarveLog(path, since_version=int(version.max()))
    _groove(engine, 6.0, 200)
    assert log.append(bone.grid.swept, bone.grid.brick_version) > 0
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)


def test_damage_in_the_middle_loses_only_what_it_covers(tmp_path, carved):
    bone, engine = carved
    path = tmp_path / "carve.log"
    sizes = _records(path, bone, engine, (3.0, 6.0, 9.0, 12.0))
    clean = read_carving(path)
    assert clean.scan.version == 2 and clean.scan.log_id == 77 and not clean.scan.damaged
    data = bytearray(path.read_bytes())
    for k in range(16):  # 16 flipped bytes in the second record
        data[sizes[0] + 100 + 7 * k] ^= 0xFF
    path.write_bytes(bytes(data))
    found = read_carving(path)
    # One small record lost (records hold RECORD_BRICKS bricks), the rest read on.
    ((at, n),) = found.scan.damaged
    assert at == sizes[0] and n <= 16 + RECORD_BRICKS * BRICK_BYTES
    assert found.scan.tail == 0
    assert len(found.scan.records) == len(clean.scan.records) - 1
    keys = {tuple(i) for i in found.index.tolist()}
    assert keys <= {tuple(i) for i in clean.index.tolist()}
    data[:] = path.read_bytes()
    data[sizes[1]:sizes[1] + 4096] = np.random.default_rng(1).bytes(4096)
    path.write_bytes(bytes(data))
    worse = read_carving(path)
    assert worse.scan.damaged_bytes >= n + 4096
    assert len(worse.scan.records) >= len(clean.scan.records) - 3
    data[0] ^= 0xFF  # the header
    path.write_bytes(bytes(data))
    assert read_carving(path).scan.header_damaged


def test_contacts_are_logged_counted_once_and_closed_up_after_damage(tmp_path):
    path = tmp_path / "carve.log"
    log = CarveLog(path, log_id=5)
    rows = np.arange(40.0).reshape(8, 5)
    empty = (np.zeros((0, 3), int), np.zeros(0, int), np.zeros((0, 8, 8, 8), np.uint8))
    log.append_carving(*empty, 0, (0, rows[:3]))
    log.append_carving(*empty, 0, (0, rows[:5]))  # the first three again: not written twice
    log.append_carving(*empty, 0, (5, rows[5:]))
    content = read_carving(path)
    assert sorted(content.contacts) == list(range(8)) and content.contacts_begun == 8
    first, got = content.contact_rows
    assert first == 0 and np.array_equal(got, rows)
    # The second record lost: the contacts after it are numbered on from the first ones.
    data = bytearray(path.read_bytes())
    head = 20 + 16 + 3 * 48
    data[head + 20] ^= 1
    path.write_bytes(bytes(data))
    damaged = read_carving(path)
    first, got = damaged.contact_rows
    assert damaged.contacts_begun == 6 and np.array_equal(got[-3:], rows[5:])


def test_a_failed_append_leaves_the_log_as_it_was(tmp_path, carved, monkeypatch):
    import errno
    import os

    bone, engine = carved
    path = tmp_path / "carve.log"
    log = CarveLog(path)
    _groove(engine, 3.0, 150)
    log.append(bone.grid.swept, bone.grid.brick_version)
    before = path.read_bytes()
    _groove(engine, 6.0, 150)
    real_fsync = os.fsync

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError):
        log.append(bone.grid.swept, bone.grid.brick_version)
    monkeypatch.setattr(os, "fsync", real_fsync)
    assert path.read_bytes() == before
    assert log.append(bone.grid.swept, bone.grid.brick_version) > 0  # retried: all of it
    fresh = phantom("workpiece", 0.2)
    apply_log(fresh.grid, *read_log(path))
    assert np.array_equal(fresh.grid.swept, bone.grid.swept)
