"""Files written whole or not at all (``server.whole_files``): on a real full disk (a small
tmpfs) nothing is left behind, and the failure says how much was written and what is free."""

from __future__ import annotations

import errno
import os

import pytest

from burrforce.server.whole_files import (
    DiskFull,
    WholeFile,
    is_disk_full,
    reserve,
    write_reserved,
    write_whole,
)
from support.tmpfs import fill, free_bytes, small_tmpfs


@pytest.fixture()
def disk(tmp_path):
    with small_tmpfs(tmp_path / "disk", "1m") as folder:
        yield folder


def test_a_file_appears_whole_with_its_mode_and_no_temporary_beside_it(tmp_path):
    path = write_whole(tmp_path / "a.bin", b"x" * 1000, permissions=0o640)
    assert path.read_bytes() == b"x" * 1000
    assert os.stat(path).st_mode & 0o777 == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_an_error_in_the_block_keeps_the_old_file_and_leaves_no_temporary(tmp_path):
    path = write_whole(tmp_path / "a.bin", b"old")
    with pytest.raises(RuntimeError), WholeFile(path) as f:
        f.write(b"new, half")
        raise RuntimeError("the writer failed")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_a_fixed_part_name_is_used_and_removed(tmp_path):
    w = WholeFile(tmp_path / "chunk-000001.npy", part_name="chunk-000001.npy.part")
    w.write(b"rows")
    assert (tmp_path / "chunk-000001.npy.part").exists()
    w.commit()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["chunk-000001.npy"]


def test_a_full_disk_is_disk_full_and_leaves_nothing(disk):
    fill(disk, leave_bytes=100_000)
    before = sorted(p.name for p in disk.iterdir())
    with pytest.raises(DiskFull) as caught, WholeFile(disk / "big.bin") as f:
        for _ in range(100):
            f.write(bytes(10_000))
    err = caught.value
    assert is_disk_full(err) and err.errno == errno.ENOSPC
    assert err.path == disk / "big.bin"
    assert 0 < err.written_bytes <= 1_000_000
    assert err.free_bytes is not None and err.free_bytes >= 90_000  # the room came back
    assert sorted(p.name for p in disk.iterdir()) == before


def test_a_disk_with_no_room_at_all_leaves_not_even_an_empty_file(disk):
    fill(disk)
    assert free_bytes(disk) == 0
    before = sorted(p.name for p in disk.iterdir())
    with pytest.raises(DiskFull):
        write_whole(disk / "x.json", b"{}" * 5000)
    assert sorted(p.name for p in disk.iterdir()) == before


def test_reserved_room_is_there_when_the_disk_filled_up_meanwhile(disk):
    held = reserve(disk / ".summary-reserve", 16 << 10)
    fill(disk)
    with pytest.raises(DiskFull):
        write_whole(disk / "other.json", b"x" * 8192)
    write_reserved(held, disk / "summary.json", b'{"rows": 7}\n')
    assert (disk / "summary.json").read_bytes() == b'{"rows": 7}\n'
    assert not held.exists()
