"""Going back over a groove (bone.history): retracing, reversing and re-entering a groove the
burr cut give no spindle power or force where nothing is left to remove; widening it cuts the
new bone as fresh bone is cut (∫ P dt = Us × removed). Real engine, real voxels."""

from __future__ import annotations

import numpy as np
import pytest

from burrforce.server.bench.groove import groove_block, oblique_rotation
from burrforce.server.bench.retrace import (
    CENTRE_Z_MM,
    RPM,
    UP,
    groove_passes,
    retrace_rows,
    stroke,
)
from burrforce.server.bone import BoneEngine, ShaftParams
from burrforce.server.bone.history import BurrPath

Z = CENTRE_Z_MM


def engine_on(oblique: bool) -> BoneEngine:
    grid = groove_block(0.1, oblique_rotation() if oblique else None)
    return BoneEngine(grid, shaft=ShaftParams(length_mm=0.0))


@pytest.fixture(scope="module", params=[False, True], ids=["aligned", "oblique"])
def passes(request):
    """A groove cut from x = 3 to 9 mm, then gone over again (``groove_passes``)."""
    result = groove_passes(engine_on(request.param))
    assert result["first"]["power_W"] > 5.0 and result["first"]["removed_mm3"] > 5.0
    return result


@pytest.mark.parametrize("name", ["reverse", "retrace", "descend", "reenter"])
def test_going_back_over_a_groove_feels_no_bone(passes, name):
    """Reversing along it, retracing it, coming back down into it after lifting out (spindle
    off in between) and cutting along it again: nothing is removed, and the power and the
    force stay within 1 % of the first pass's (they were 10 % before the path)."""
    first, numbers = passes["first"], passes[name]
    assert numbers["removed_mm3"] < 1e-3
    assert numbers["power_W"] <= 0.01 * first["power_W"]
    assert numbers["force_N"] <= 0.01 * first["force_N"]


def test_widening_a_groove_cuts_the_new_bone_like_fresh_bone(passes):
    """1 mm to the side, from outside the block: the burr removes about half a groove's bone;
    the spindle's energy is that bone's Us × volume (as on fresh bone), not less (the path
    hiding fresh bone) nor more (ghost power from the old groove's wall)."""
    widen = passes["widen"]
    assert 0.3 * passes["first"]["removed_mm3"] < widen["removed_mm3"]
    assert widen["spindle_J"] == pytest.approx(widen["removal_J"], rel=0.03)


def test_bench_rows_report_the_targets():
    rows = retrace_rows(grids=("aligned",))
    assert {r["case"] for r in rows} == {"reverse", "retrace", "descend", "reenter", "widen"}
    assert all(r["ok"] for r in rows), rows


def test_fresh_groove_energy_balance_holds_with_the_path():
    """Entering through a side face and cutting a whole groove on a fresh block: the path
    (every cut known) gives the same energy balance as before it existed (≤ 1.2 %)."""
    engine = engine_on(False)
    run = stroke(engine, (-3.0, 6.0, Z), (9.0, 6.0, Z))
    assert run["spindle_J"] == pytest.approx(run["removal_J"], rel=0.012)


def test_a_resumed_bone_falls_back_to_the_voxels():
    """An engine made over a bone that was cut before it (a resumed session) does not know
    those cuts: it uses the voxels' availability there (the old behaviour), and its own
    path on top of it."""
    engine = engine_on(False)
    first = stroke(engine, (3.0, 6.0, Z), (9.0, 6.0, Z))
    resumed = BoneEngine(engine.grid, shaft=ShaftParams(length_mm=0.0))
    again = stroke(resumed, (9.0, 6.0, Z), (3.0, 6.0, Z))
    assert again["removed_mm3"] < 1e-3
    # The voxels alone report ghost power (measured 10 % before the path existed) ...
    assert 0.02 * first["power_W"] < again["power_W"] < 0.2 * first["power_W"]
    # ... and once this engine has been over the groove itself, its path knows it is empty
    # (its own capsules multiply the voxels' availability to 0).
    third = stroke(resumed, (3.0, 6.0, Z), (9.0, 6.0, Z))
    assert third["power_W"] <= 0.01 * first["power_W"]


def test_the_path_stores_a_straight_stroke_as_one_segment_and_wraps():
    path = BurrPath((np.zeros(3), np.full(3, 10.0)), carved_before=False, segments=4)
    engine = engine_on(False)
    engine.path = path
    stroke(engine, (3.0, 6.0, Z), (9.0, 6.0, Z))
    assert path.segments == 0  # still one open run, not stored
    # Jumps (far apart, each carving) close runs: the ring fills, wraps, and what it dropped
    # becomes unknown ground.
    for x in (1.0, 4.0, 7.0, 10.0, 1.0, 4.0):
        engine.step((x, 3.0, Z), UP, (10.0, 0.0, 0.0), RPM)
    assert path.segments == 4
    from burrforce.server.bone.history import M_UNKNOWN
    lo = path.meta[M_UNKNOWN:M_UNKNOWN + 3]
    hi = path.meta[M_UNKNOWN + 3:M_UNKNOWN + 6]
    assert (lo <= hi).all()


def test_moving_in_air_leaves_no_path():
    """Only carving near bone is recorded: a hand wandering above the block at cutting speed
    must not fill the ring and push the real cuts out of it."""
    engine = engine_on(False)
    for i in range(2000):
        x = 2.0 + 8.0 * abs(np.sin(i * 0.01))
        engine.step((x, 6.0 + np.cos(i * 0.013), Z + 5.0), UP, (10.0, 0.0, 0.0), RPM)
    assert engine.path.segments == 0
