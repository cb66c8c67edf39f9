"""``BoneEngine.step_raw``'s two ways into the tick: the call bound to the engine's buffers
(``hot_kernel.DirectCall``, float64 contiguous vectors) and numba's dispatch for anything else,
and the binding renewed when what it was bound to is replaced."""

from __future__ import annotations

import dataclasses

import numpy as np

from burrforce.server.bone import BoneEngine, BoneGrid, ShaftParams, workpiece_block
from burrforce.server.bone.carve import TOUCH_VISITED
from burrforce.server.bone.materials import CORTICAL, CORTICAL_LABEL, Material, MaterialTable
from burrforce.server.bone.tick import bone_tick

RPM = 60000.0
TICKS = 60
SWITCH_AT = 25
#: A burr 1.5 mm deep, its axis 10° above the surface, fed at 3 mm/s across it (one tick per
#: millisecond): its shaft lies in the uncut bone beside the groove, so it touches.
AXIS_W = np.array([-np.cos(np.radians(10.0)), 0.0, np.sin(np.radians(10.0))])
FEED_W = np.array([0.0, 3.0, 0.0])


def block() -> BoneGrid:
    return workpiece_block(0.1, lo_mm=(0, 0, -4), hi_mm=(8, 8, 0), margin_mm=1.0,
                           offset_voxels=(0.31, 0.17, 0.43))


def groove_pose(grid: BoneGrid, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tick i of a groove in the grid frame, as fresh contiguous float64 (3,) arrays."""
    centre = np.array([5.0, 3.0, 0.5]) + FEED_W * (i * 1e-3)
    return (grid.to_grid_point(centre), grid.to_grid_vector(AXIS_W), grid.to_grid_vector(FEED_W))


def strided(v: np.ndarray) -> np.ndarray:
    """The same three values as a non-contiguous float64 view (stride 16 bytes)."""
    backing = np.full(6, np.nan)
    backing[::2] = v
    view = backing[::2]
    assert not view.flags.c_contiguous
    return view


def outputs(engine: BoneEngine, removed: bool, visited: bool = True) -> np.ndarray:
    """Everything a tick answers; ``visited=False`` leaves out the count of voxels the carve
    examined (a cost statistic)."""
    touch = np.asarray(engine.touch, float)
    if not visited:
        touch = np.delete(touch, TOUCH_VISITED)
    return np.concatenate([engine.out, engine.shaft_out, touch, [float(removed)]])


def test_numba_dispatch_answers_as_the_bound_call_to_the_last_bit() -> None:
    """Vectors the bound call does not take (non-contiguous views) go through numba's
    dispatch. Fed the same groove, both engines give the same outputs, carve the same voxels
    and keep the same path, bit for bit."""
    grid_a, grid_b = block(), block()
    a, b = BoneEngine(grid_a), BoneEngine(grid_b)
    for i in range(TICKS):
        centre, axis, feed = groove_pose(grid_a, i)
        removed_a = a.step_raw(centre, axis, feed, RPM)
        removed_b = b.step_raw(strided(centre), strided(axis), strided(feed), RPM)
        np.testing.assert_array_equal(outputs(a, removed_a), outputs(b, removed_b),
                                      err_msg=f"tick {i}")
    assert a.out[0:3].any(), "the groove never cut: the comparison says nothing"
    np.testing.assert_array_equal(grid_a.swept, grid_b.swept)
    np.testing.assert_array_equal(grid_a.brick_version, grid_b.brick_version)
    np.testing.assert_array_equal(a.path.ring, b.path.ring)
    assert grid_a.version == grid_b.version > 0
    # The second engine really went through the dispatcher: a signature for non-contiguous
    # ('A' layout) vectors was compiled or loaded from the cache.
    assert any(getattr(t, "layout", None) == "A" for sig in bone_tick.signatures
               for t in sig), bone_tick.signatures


def test_the_bound_call_follows_materials_shaft_and_params_replaced_mid_groove() -> None:
    """An engine whose material table, shaft and params are replaced mid-groove answers, from
    that tick on, as an engine that had them from the start: the bound call is bound again to
    the new tables (a stale binding would keep the old Us and K, or the old shaft)."""
    harder = MaterialTable({CORTICAL_LABEL: Material(
        "cortical", 2.0 * CORTICAL.us_n_mm2, 0.9)})
    shaft_before = ShaftParams(length_mm=0.0)
    shaft_after = ShaftParams()
    grid_s, grid_f = block(), block()
    switched = BoneEngine(grid_s, shaft=shaft_before)
    fixed = BoneEngine(grid_f, materials=harder, shaft=shaft_after)
    compared = 0
    for i in range(TICKS):
        if i == SWITCH_AT:
            switched.set_materials(harder)
            switched.shaft = shaft_after
            # Equal params, a new object: the coverage cache is replaced with them.
            switched.params = dataclasses.replace(switched.params)
        centre, axis, feed = groove_pose(grid_s, i)
        removed_s = switched.step_raw(centre, axis, feed, RPM)
        removed_f = fixed.step_raw(centre, axis, feed, RPM)
        assert removed_s == removed_f
        if i >= SWITCH_AT:
            # New params make the next carve examine the burr's whole neighbourhood again
            # (``forget_last_carve``), so only the count of voxels it examined may differ.
            np.testing.assert_array_equal(outputs(switched, removed_s, visited=False),
                                          outputs(fixed, removed_f, visited=False),
                                          err_msg=f"tick {i}")
            compared += 1
        elif i > 5:
            # Before the switch the two differ (half the Us, no shaft): the test can tell.
            assert not np.array_equal(switched.out, fixed.out)
    assert compared == TICKS - SWITCH_AT
    assert fixed.shaft_out.any(), "the shaft never touched: its half of the test says nothing"
    np.testing.assert_array_equal(grid_s.swept, grid_f.swept)
