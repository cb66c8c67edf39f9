"""``python -m burrforce.server.bench.tick_profile`` in its wall-time mode (the callgrind mode is
the same ticks under valgrind): both cutters plough the groove and report a tick time."""

from __future__ import annotations

import re

import pytest

from burrforce.server.bench import tick_profile


@pytest.mark.parametrize("cutter", ["abrasive", "fluted"])
def test_wall_time_per_tick_for_each_cutter(cutter, capsys):
    assert tick_profile.main(["--no-callgrind", "--ticks", "20", "--cutter", cutter]) == 0
    line = capsys.readouterr().out
    assert f" {cutter} tick: " in line
    p50, p99 = map(float, re.search(r"p50 ([\d.]+) µs, p99 ([\d.]+) µs", line).groups())
    assert 0.0 < p50 <= p99


def test_the_carve_alone_is_the_round_abrasive_burrs():
    with pytest.raises(SystemExit, match="round abrasive"):
        tick_profile.main(["--no-callgrind", "--ticks", "5", "--part", "carve",
                           "--cutter", "fluted"])
