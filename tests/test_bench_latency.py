"""``bench latency`` on one chunk per mode: every mode answered through its own server, the
hogged modes ran beside the busy task, and the results file says so (numbers, not timings:
the machine is shared)."""

from __future__ import annotations

import json
import math

from burrforce.server.bench import latency


def test_every_mode_answers_and_the_results_name_them(tmp_path):
    result = latency.run(500, 500, 0.4)
    rows = {(r["mode"], r["pacing"]): r for r in result["runs"]}
    assert set(rows) == {(mode, pacing) for mode in latency.MODES
                         for pacing in ("1 kHz", "back-to-back")}
    for (mode, _), row in rows.items():
        assert row["samples"] + row["lost"] <= 500
        assert row["lost"] <= 25, row  # a 0.25 s reply timeout: only a stalled machine loses
        if mode in latency.CUTTING_MODES:
            # The raster starts in air; every cutting mode reaches the bone within the chunk.
            assert row["samples"] > 0 and row["cutting_fraction"] > 0.3, row
        assert 0 < row["p50_us"] <= row["p99_us"] <= row["max_us"], row
    assert math.isfinite(result["hogged_p99_us"]) and math.isfinite(
        result["hogged_blocking_p99_us"])
    # The waking loop beside the busy task: every packet it expected was polled for, skipped
    # or waited for, and its counters are reported.
    wake = result["hogged_wake_counters"]
    assert {"wake_caught", "wake_missed", "wake_quiet", "wake_preempted"} <= set(wake)
    assert sum(v for k, v in wake.items() if k != "wake_poll_ms") > 0
    md, js = latency.write_results(result | {"page": {"skipped": "test"}}, tmp_path)
    text = md.read_text()
    assert "| hogged | 1 kHz |" in text and "| hogged blocking | back-to-back |" in text
    assert "A CPU-bound task on the servers' CPU" in text
    assert json.loads(js.read_text())["hogged_p50_us"] == result["hogged_p50_us"]
