"""The live view's plots (server/ui/static/plots.js) run in Node with uPlot stubbed: they hold
the last 10 s of a session's telemetry, as the live view's docs say, whatever the samples'
order — a torn sample just behind the last one is skipped, not a reason to start over."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

PLOTS = Path(__file__).resolve().parent.parent / "server" / "ui" / "static" / "plots.js"

_HARNESS = """
globalThis.window = { uPlot: class { constructor(o, d, b) {} setSize() {} setData() {} } };
globalThis.document = { createElement: () => ({ dataset: {}, className: "" }) };
globalThis.ResizeObserver = class { observe() {} };
const { LivePlots } = await import(process.argv[1]);
const plots = new LivePlots({ appendChild() {}, clientWidth: 500 });
const samples = JSON.parse(process.argv[2]);
for (const s of samples) plots.push(s);
const xs = plots.charts[0].data[0];
console.log(JSON.stringify({ first: xs[0], last: xs[xs.length - 1], n: xs.length }));
"""


def _window(samples: list[dict]) -> dict:
    node = shutil.which("node") or shutil.which("nodejs")
    if node is None:
        pytest.skip("node is not installed (Debian: nodejs)")
    out = subprocess.run([node, "--input-type=module", "-e", _HARNESS, str(PLOTS),
                          json.dumps(samples)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def _sample(t_s: float) -> dict:
    return {"t_recv_s": t_s, "packet": True, "force_N": [0.0, 0.0, 0.0]}


def test_the_plots_hold_the_last_ten_seconds():
    # 12 s of telemetry at 30 Hz, as the page receives it, with a torn sample now and then.
    times = [1000.0 + i / 30 for i in range(360)]
    samples = []
    for i, t in enumerate(times):
        samples.append(_sample(t))
        if i % 50 == 49:
            samples.append(_sample(t - 0.02))  # read while the loop wrote it
    window = _window(samples)
    assert window["last"] == pytest.approx(times[-1] - 1000.0)
    assert window["last"] - window["first"] == pytest.approx(10.0, abs=0.05)


def test_another_clock_starts_the_window_again_and_no_packet_is_no_point():
    samples = [_sample(1000.0 + i / 30) for i in range(90)]
    samples.append({"t_recv_s": 0.0, "packet": False, "force_N": [0.0, 0.0, 0.0]})
    samples += [_sample(5.0 + i / 30) for i in range(30)]  # a restarted server's clock
    window = _window(samples)
    assert window["n"] == 30 and window["first"] == 0.0
