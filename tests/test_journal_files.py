"""The journal's small files: ``state.bin`` (two slots written in place, the newer intact one
read) and ``session.json`` (checksummed; format 1 still read; a bad key refused)."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.api.journal_record import RecordError, read_record, sealed
from burrforce.server.api.journal_state import SLOT_BYTES, JournalState, StateFile, read_state


def _state(version: int) -> JournalState:
    return JournalState(7, 1.5, version, {"1": 65025.0 * version}, 2,
                        {"bytes": 100, "records": 1, "bricks": 3, "version": version,
                         "contacts": 2})


def test_the_newer_intact_slot_is_read(tmp_path):
    path = tmp_path / "state.bin"
    state = StateFile(path)
    state.create(_state(1))
    assert read_state(path) == _state(1)
    size = path.stat().st_size
    state.write(_state(2))
    state.write(_state(3))
    assert read_state(path) == _state(3)
    assert path.stat().st_size == size  # written in place
    # A write cut short (a crash in the middle of the newer slot): the other one, a pass
    # older, is read.
    data = bytearray(path.read_bytes())
    newer = (state.sequence % 2) * SLOT_BYTES
    data[newer + 40] ^= 0xFF
    path.write_bytes(bytes(data))
    assert read_state(path) == _state(2)
    path.write_bytes(b"")
    assert read_state(path) is None
    assert read_state(tmp_path / "missing") is None


@settings(max_examples=examples(40), deadline=None)
@given(st.binary(max_size=2 * SLOT_BYTES + 10))
def test_any_bytes_read_as_a_state_never_raise(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("fuzz") / "state.bin"
    path.write_bytes(data)
    assert read_state(path) is None or isinstance(read_state(path), JournalState)


def _record(**changes) -> dict:
    record = {"format": "burrforce-journal", "format_version": 2, "id": 1,
              "key_hex": "ab" * 32, "source": {"source": "phantom:workpiece", "kind": None,
                                                "voxel_mm": 0.2, "spacing_mm": None,
                                                "path": None},
              "parameters": {}, "features": {}, "primary_label": 1, "overrides": {},
              "calibrations": {}, "created": 1.0, "next_stream": 5, "worker": 0,
              "bone_generation": 3, "carve_log": 9}
    record.update(changes)
    return record


def test_a_sealed_record_reads_back_and_any_change_is_caught(tmp_path):
    path = tmp_path / "session.json"
    path.write_text(sealed(_record()))
    assert read_record(path)["key_hex"] == "ab" * 32
    text = path.read_text().replace("ab" * 32, "ac" + "ab" * 31)  # still valid hex
    path.write_text(text)
    with pytest.raises(RecordError, match="checksum"):
        read_record(path)


def test_format_1_records_are_read_without_a_checksum(tmp_path):
    path = tmp_path / "session.json"
    old = _record(format_version=1)
    del old["carve_log"]
    path.write_text(json.dumps(old))
    assert read_record(path)["id"] == 1


@pytest.mark.parametrize("change,match", [
    ({"key_hex": "zz" + "ab" * 31}, "invalid key"),
    ({"key_hex": ""}, "invalid key"),
    ({"key_hex": 12}, "invalid key"),
    ({"id": "1"}, "'id'"),
    ({"source": {"source": None}}, "bone source"),
    ({"format_version": 9}, "format 9"),
    ({"format": "other"}, "not a burrforce-journal"),
])
def test_a_record_that_cannot_be_trusted_is_refused(tmp_path, change, match):
    path = tmp_path / "session.json"
    path.write_text(json.dumps(_record(**{"format_version": 1, **change})))
    with pytest.raises(RecordError, match=match):
        read_record(path)


def test_unreadable_records_are_refused(tmp_path):
    path = tmp_path / "session.json"
    with pytest.raises(RecordError, match="missing"):
        read_record(path)
    path.write_bytes(b"\xff\x00{")
    with pytest.raises(RecordError, match="not JSON"):
        read_record(path)
    path.write_text("[1, 2]")
    with pytest.raises(RecordError, match="not a burrforce-journal"):
        read_record(path)
