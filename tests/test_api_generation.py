"""Bone generations (server/api/generation.py): a counter in the data directory that never
hands out a number twice — across threads, restarts, a lost count and a read-only disk."""

from __future__ import annotations

import threading

from burrforce.server.api.generation import COUNTER_FILE, bone_generation, next_generation


def test_counts_from_one_and_persists_across_restarts(tmp_path):
    assert [next_generation(tmp_path) for _ in range(3)] == [1, 2, 3]
    assert (tmp_path / COUNTER_FILE).read_text().strip() == "3"
    # A restarted server reads the count back: it goes on, never repeats.
    assert next_generation(tmp_path) == 4
    other = tmp_path / "other"
    other.mkdir()
    assert next_generation(other) == 1  # a count per data directory


def test_threads_never_share_a_generation(tmp_path):
    got: list[int] = []
    lock = threading.Lock()

    def take() -> None:
        for _ in range(20):
            g = next_generation(tmp_path)
            with lock:
                got.append(g)
    threads = [threading.Thread(target=take) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(got) == list(range(1, 81))


def test_a_lost_count_continues_above_anything_counted(tmp_path):
    for _ in range(5):
        next_generation(tmp_path)
    (tmp_path / COUNTER_FILE).write_text("garbage")
    g = next_generation(tmp_path)
    assert 10**15 < g < 2**53  # microseconds since the epoch: past any count, exact in JSON
    assert next_generation(tmp_path) == g + 1


def test_an_unwritable_directory_still_gives_distinct_generations(tmp_path):
    missing = tmp_path / "gone" / "deeper"  # cannot be written: no such directory
    a, b = next_generation(missing), next_generation(missing)
    assert 10**15 < a < b


def test_bone_generation_reads_the_bone_info():
    class Session:
        bone_info: dict | None = None

    s = Session()
    assert bone_generation(s) is None
    s.bone_info = {"generation": 7}
    assert bone_generation(s) == 7
