"""``bench latency``'s live-view part on a few chunks: rows for both modes, and the open chunks
saw the page draw and receive telemetry (numbers, not timings: the machine is shared)."""

from __future__ import annotations

import math

import pytest

from benchmarks import latency_page
from support import chromium


def test_the_page_part_measures_both_modes_and_the_open_page_was_live():
    reason = chromium.missing()
    if reason is not None:
        pytest.skip(reason)
    page = latency_page.run(600, 0.2, chunk=300)
    assert page["skipped"] is None
    closed, opened = page["runs"]
    assert (closed["mode"], opened["mode"]) == latency_page.MODES
    for row in (closed, opened):
        assert row["pacing"] == "1 kHz"
        assert row["samples"] + row["lost"] <= 600
        # The groove starts in air (its first 0.4 s: most of the first closed chunk).
        assert row["samples"] > 0 and row["cutting_fraction"] > 0.25
        assert 0 < row["p50_us"] <= row["p99_us"] <= row["p999_us"] <= row["max_us"]
        assert all(math.isfinite(row[k]) for k in ("p50_us", "p99_us", "p999_us"))
        assert row["wall_s"] > 0.25 and row["hot_loop_cpu_pct"] > 0
    assert "frames" not in closed
    assert opened["frames"] > 0 and opened["telemetry_samples"] > 0
    assert opened["browser_cpu_pct"] > 0 and opened["wall_s"] > 0.5
    assert page["page_errors"] == []
    text = "\n".join(latency_page.markdown(page))
    assert "| page open |" in text and "| page closed |" in text
