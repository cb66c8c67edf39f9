"""``burrforce bench sessions``: a short run through the real command (a real ``serve`` per
session count, real sockets), checked for structure and counts, never for timings."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from scheduling import FIFO_REASON, fifo_permitted

from burrforce.server.bench import sessions as bench_sessions
from burrforce.server.bench import stations
from burrforce.server.cli import main
from burrforce.server.realtime import HOT_LOOP_PRIORITY

REQUIRED = ("sessions", "workers", "sent", "answered", "lost", "late", "rtt_p50_us",
            "rtt_p99_us", "rtt_p999_us", "send_late_p99_us", "generator_cpu_pct",
            "server_cpu_pct", "server_cpu_per_session_pct")


@pytest.fixture(scope="module")
def smoke(tmp_path_factory) -> tuple[list[dict], dict, str]:
    out = tmp_path_factory.mktemp("sessions")
    import contextlib
    import io

    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(["bench", "sessions", "--sessions", "1,2", "--seconds", "1",
                     "--warmup-s", "0.3", "--phases", "independent", "--json",
                     "--out", str(out)])
    assert code == 0
    written = json.loads((out / "sessions.json").read_text())
    return json.loads(printed.getvalue()), written, (out / "sessions.md").read_text()


def test_rows_have_the_required_keys_and_consistent_counts(smoke):
    rows, written, _ = smoke
    assert [r["sessions"] for r in rows] == [1, 2]
    assert written["rows"] == rows
    for r in rows:
        assert set(REQUIRED) <= set(r)
        assert r["phases"] == "independent" and r["realtime_workers"] == 0
        assert r["workers"] >= 1 and len(r["worker_pids"]) == r["workers"]
        # One POSE per session per tick of the window (the schedule never skips a tick).
        assert r["sent"] == r["sessions"] * round(1.0 * 1000)
        assert r["lost"] >= 0 and r["answered"] + r["lost"] == r["sent"]
        assert 0 <= r["late"] <= r["answered"]
        assert r["server_cpu_pct"] >= 0 and r["generator_cpu_pct"] >= 0
        assert r["server_cpu_per_session_pct"] == pytest.approx(
            r["server_cpu_pct"] / r["sessions"])
        # Read once a tick only where the kernel stamps arrivals (Linux does): then every
        # round trip comes from a stamp. The POSEs encoded ahead of the run still cut.
        assert r["read"] == "tick" and r["kernel_stamped_fraction"] == 1.0
        assert r["cutting_fraction"] > 0.0
        if r["answered"]:
            assert 0 < r["rtt_p50_us"] <= r["rtt_p99_us"] <= r["rtt_p999_us"] <= r["rtt_max_us"]
            assert r["send_late_p50_us"] >= 0


def test_the_markdown_has_a_table_per_count_the_machine_and_the_target(smoke):
    _, written, md = smoke
    assert "## N = 1 " in md and "## N = 2 " in md
    assert written["machine"] in md
    assert bench_sessions.TARGET in md


def test_independent_stations_have_their_own_phase_and_rate():
    offsets, periods = stations.station_clocks(64, "independent", seed=7)
    assert offsets.shape == periods.shape == (64,)
    assert 0 <= offsets.min() and offsets.max() < stations.PERIOD_NS
    assert np.ptp(offsets) > 0.5 * stations.PERIOD_NS   # spread over the period
    spread = np.abs(periods / stations.PERIOD_NS - 1) * 1e6
    assert spread.max() <= stations.RATE_SPREAD_PPM and spread.max() > 10.0
    again = stations.station_clocks(64, "independent", seed=7)
    assert np.array_equal(again[0], offsets) and np.array_equal(again[1], periods)
    offsets, periods = stations.station_clocks(8, "aligned")
    assert not offsets.any() and np.all(periods == stations.PERIOD_NS)
    with pytest.raises(ValueError, match="phases"):
        stations.station_clocks(8, "random")


def test_session_counts_are_parsed_and_checked():
    assert bench_sessions._counts("1, 2,16") == [1, 2, 16]
    for bad in ("", "0", "1,x", "300"):
        with pytest.raises(Exception, match="session count"):
            bench_sessions._counts(bad)


def test_worker_pids_come_from_the_pool_else_from_the_single_loop():
    pool = {"supervisor": {"pid": 11}, "workers": [{"index": 0, "pid": 21},
                                                   {"index": 1, "pid": 22}]}
    assert bench_sessions._worker_pids(pool) == [21, 22]
    # A server without a pool (no ``workers`` in its health): the supervisor's loop.
    assert bench_sessions._worker_pids({"supervisor": {"pid": 11}}) == [11]
    with pytest.raises(RuntimeError, match="no hot-loop process"):
        bench_sessions._worker_pids({"supervisor": {"pid": None}, "workers": []})


@pytest.mark.skipif(not fifo_permitted(), reason=FIFO_REASON)
def test_realtime_reaches_serve_and_the_generator(tmp_path, capsys):
    code = main(["bench", "sessions", "--sessions", "1", "--seconds", "0.5", "--warmup-s",
                 "0.2", "--workers", "2", "--realtime", "--json", "--out", str(tmp_path)])
    assert code == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["realtime_workers"] == row["workers"] == 2 and row["answered"] > 0
    md = (tmp_path / "sessions.md").read_text()
    assert "--realtime)" in md and "| loops under SCHED_FIFO | 2 of 2 |" in md
    # The generator ran above the loops, and went back to the normal scheduler after.
    assert row["generator_realtime"] is fifo_permitted(HOT_LOOP_PRIORITY + 1)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_reading_each_reply_as_it_comes_from_loops_that_do_not_wake_ahead(tmp_path, capsys):
    """``--read reply``: the generator wakes for each reply (the fallback where the kernel
    stamps nothing); the round trip still ends at the arrival, no later than the read.
    ``--wake-ahead-us 0`` reaches ``serve``: its loops block until each datagram."""
    code = main(["bench", "sessions", "--sessions", "1", "--seconds", "0.5", "--warmup-s",
                 "0.2", "--read", "reply", "--wake-ahead-us", "0", "--json", "--out",
                 str(tmp_path)])
    assert code == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["read"] == "reply" and row["lost"] == 0 and row["sent"] == 500
    assert 0 < row["rtt_p50_us"] <= row["read_p50_us"]
    md = (tmp_path / "sessions.md").read_text()
    assert "| replies read | per reply |" in md and "--wake-ahead-us 0)" in md
    assert json.loads((tmp_path / "sessions.json").read_text())["wake_ahead_us_option"] == 0
