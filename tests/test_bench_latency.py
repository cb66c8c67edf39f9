"""``bench latency`` on one chunk per mode: every mode answered through its own server, the
hogged modes ran beside the busy task, and the results file says so (numbers, not timings:
the machine is shared)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time

from scheduling import fifo_permitted

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
            # The raster starts in air (a third of a second at 1 kHz); every cutting mode
            # reaches the bone within the chunk.
            assert row["samples"] > 0 and row["cutting_fraction"] > 0.1, row
        assert 0 < row["p50_us"] <= row["p99_us"] <= row["max_us"], row
    assert math.isfinite(result["hogged_p99_us"]) and math.isfinite(
        result["hogged_blocking_p99_us"])
    # The waking loop beside the busy task: every packet it expected was polled for, skipped
    # or waited for, and its counters are reported.
    wake = result["hogged_wake_counters"]
    assert {"wake_caught", "wake_missed", "wake_quiet", "wake_preempted"} <= set(wake)
    assert sum(v for k, v in wake.items() if k != "wake_poll_ms") > 0
    # The realtime loops got SCHED_FIFO where this machine allows it, and the file says which.
    assert set(result["realtime_granted"]) == {"realtime", "hogged realtime"}
    assert set(result["realtime_granted"].values()) == {fifo_permitted()}
    md, js = latency.write_results(result | {"page": {"skipped": "test"}}, tmp_path)
    text = md.read_text()
    assert "| hogged | 1 kHz |" in text and "| hogged blocking | back-to-back |" in text
    assert "| realtime | 1 kHz |" in text and "| hogged realtime | 1 kHz |" in text
    assert "A CPU-bound task on the servers' CPU" in text
    assert ("SCHED_FIFO was NOT permitted here" in text) is not fifo_permitted()
    assert json.loads(js.read_text())["hogged_p50_us"] == result["hogged_p50_us"]


def test_the_hog_dies_with_the_bench():
    """A bench killed outright (no ``finally``) leaves no busy loop burning a core."""
    parent = subprocess.Popen(
        [sys.executable, "-c",
         "import os, subprocess, sys, time\n"
         "from burrforce.server.bench.latency import HOG\n"
         "hog = subprocess.Popen([sys.executable, '-c', HOG, str(os.getpid())])\n"
         "print(hog.pid, flush=True)\n"
         "time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True)
    hog_pid = int(parent.stdout.readline())
    time.sleep(0.3)  # the hog is spinning
    assert _alive(hog_pid)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 10.0
    while _alive(hog_pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(hog_pid)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not reaped by its init, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False
