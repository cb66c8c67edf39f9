"""``python -m benchmarks.tick_profile`` in its wall-time mode (the callgrind mode is
the same ticks under valgrind): every burr ploughs the groove and reports a tick time."""

from __future__ import annotations

import re

import pytest

from benchmarks import tick_profile


@pytest.mark.parametrize("burr", list(tick_profile.BURR_CHOICES))
def test_wall_time_per_tick_for_each_burr(burr, capsys):
    assert tick_profile.main(["--no-callgrind", "--ticks", "20", "--burr", burr]) == 0
    line = capsys.readouterr().out
    assert f" {burr} tick: " in line
    p50, p99 = map(float, re.search(r"p50 ([\d.]+) µs, p99 ([\d.]+) µs", line).groups())
    assert 0.0 < p50 <= p99


def test_the_carve_alone_is_the_round_abrasive_burrs():
    with pytest.raises(SystemExit, match="round abrasive"):
        tick_profile.main(["--no-callgrind", "--ticks", "5", "--part", "carve",
                           "--burr", "round-fluted"])
