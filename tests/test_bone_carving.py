"""Carving: partial-volume removal, neighbourhood only, bricks, versions, materials, events."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.bone import (
    BoneEngine,
    BoneGrid,
    Material,
    MaterialTable,
    ShaftParams,
    workpiece_block,
)
from burrforce.server.bone.bricks import BRICK
from burrforce.server.model.shapes import Barrel, Burr

RPM = 60000.0
AXIS = (0.0, 0.0, 1.0)
STILL = (0.0, 0.0, 0.0)


def small_block(voxel_mm: float = 0.1) -> BoneGrid:
    return workpiece_block(voxel_mm, lo_mm=(0, 0, -4), hi_mm=(8, 8, 0), margin_mm=1.0,
                           offset_voxels=(0.31, 0.17, 0.43))


def engine_for(grid: BoneGrid, **kwargs) -> BoneEngine:
    return BoneEngine(grid, shaft=ShaftParams(length_mm=0.0), **kwargs)


def as_the_tick_reads(grid: BoneGrid) -> np.ndarray:
    """The swept shares the tick reads, int16: bone's, and for air (density 0) only whether a
    burr reached it (0 or 1): air is marked 255 at once where any coverage reaches it."""
    return np.where(grid.density > 0, grid.swept, np.minimum(grid.swept, 1)).astype(np.int16)


def cap_volume(radius: float, depth: float) -> float:
    return math.pi * depth * depth * (3.0 * radius - depth) / 3.0


# Partial volume at the cap's rim (bone below, burr above-inside the same voxels) errs by
# O(h²): shallow caps, where the rim weighs most, get the widest tolerance.
@pytest.mark.parametrize(("depth", "tolerance"), [(0.5, 0.015), (1.3, 0.004), (2.0, 0.002),
                                                  (3.0, 0.002)])
def test_plunge_removes_the_spherical_cap(depth, tolerance):
    grid = small_block()
    engine = engine_for(grid)
    before = grid.bone_volume_by_label_mm3()[1]
    result = engine.step((4.0, 4.0, 2.0 - depth), AXIS, STILL, RPM)
    expected = cap_volume(2.0, depth)
    assert result.removed_mm3 == pytest.approx(expected, rel=tolerance)
    assert before - grid.bone_volume_by_label_mm3()[1] == pytest.approx(result.removed_mm3,
                                                                         rel=1e-9)
    assert result.removed_mm3_by_material == {"cortical": pytest.approx(result.removed_mm3)}
    assert engine.removed_mm3_by_material()["cortical"] == pytest.approx(result.removed_mm3)


def test_cap_volume_converges_at_second_order():
    errors = []
    for voxel_mm in (0.2, 0.1):
        result = engine_for(small_block(voxel_mm)).step((4.0, 4.0, 1.5), AXIS, STILL, RPM)
        errors.append(abs(result.removed_mm3 / cap_volume(2.0, 0.5) - 1.0))
    assert errors[1] < errors[0] / 3.0


def test_carving_is_idempotent_and_versions_are_monotone():
    grid = small_block()
    engine = engine_for(grid)
    first = engine.step((4.0, 4.0, 1.5), AXIS, STILL, RPM)
    assert first.bone_version == 1 and first.removed_mm3 > 0
    swept = grid.swept.copy()
    engine.forget_last_carve()  # make it re-examine every voxel
    again = engine.step((4.0, 4.0, 1.5), AXIS, STILL, RPM)
    assert again.removed_mm3 == 0.0 and again.bone_version == 1
    assert np.array_equal(grid.swept, swept)
    moved = engine.step((4.05, 4.0, 1.5), AXIS, (50.0, 0, 0), RPM)
    assert moved.bone_version == 2 and moved.removed_mm3 > 0


def test_only_the_burr_neighbourhood_changes_and_changed_bricks_are_reported():
    grid = small_block()
    engine = engine_for(grid)
    centre = np.array([4.0, 4.0, 1.2])
    density_before = grid.density.copy()
    engine.step(centre, AXIS, STILL, RPM)
    assert np.array_equal(grid.density, density_before)  # carving never writes the original
    changed = np.argwhere(grid.swept > 0)
    centres = grid.origin_mm + changed * grid.spacing_mm
    reach = 2.0 + 0.5 * math.sqrt(3) * 0.1
    assert (np.linalg.norm(centres - centre, axis=1) <= reach + 1e-9).all()
    bricks = {tuple(b) for b in grid.changed_bricks(0)}
    removed_bricks = {tuple(i // BRICK) for i in np.argwhere(
        (grid.swept > 0) & (grid.density > 0))}
    assert bricks == removed_bricks
    assert grid.changed_bricks(1).size == 0


def test_brick_counts_stay_exact_while_carving():
    grid = small_block()
    engine = engine_for(grid)
    for i in range(60):
        engine.step((1.0 + 0.1 * i, 4.0, 1.0), AXIS, (100.0, 0, 0), RPM)
    bone, full = grid.brick_bone.copy(), grid.brick_full.copy()
    grid.recount()
    assert np.array_equal(bone, grid.brick_bone) and np.array_equal(full, grid.brick_full)


def test_below_cutting_speed_nothing_is_carved():
    grid = small_block()
    engine = engine_for(grid)
    result = engine.step((4.0, 4.0, 1.5), AXIS, (3.0, 0, 0), 1000.0)
    assert result.removed_mm3 == 0.0 and not grid.swept.any()
    assert result.cut.contact and not result.cut.cutting
    assert not result.cut.force_N.any()


def test_removal_per_material():
    density = np.full((60, 60, 40), 255, np.uint8)
    labels = np.ones(density.shape, np.uint8)
    labels[30:] = 2  # x ≥ 3 mm is the second material
    grid = BoneGrid(density, 0.1, labels=labels)
    table = MaterialTable({1: Material("cortical", 805.1, 1.3),
                           2: Material("trabecular", 300.0, 1.3)})
    engine = engine_for(grid, materials=table)
    # Burr centred on the boundary plane between the two materials (x = 2.95 mm, between the
    # voxel centres 2.9 and 3.0), cap 1 mm deep into the top face.
    top = 3.95  # the top voxel layer's upper face
    result = engine.step((2.95, 3.0, top + 1.0), AXIS, STILL, RPM)
    half = cap_volume(2.0, 1.0) / 2
    assert result.removed_mm3_by_material["cortical"] == pytest.approx(half, rel=0.01)
    assert result.removed_mm3_by_material["trabecular"] == pytest.approx(half, rel=0.01)
    expected_j = (805.1 + 300.0) * half * 1e-3
    assert engine.removal_energy_J() == pytest.approx(expected_j, rel=0.01)


def test_forbidden_contact_is_an_event_when_it_begins():
    density = np.full((80, 40, 40), 255, np.uint8)
    labels = np.ones(density.shape, np.uint8)
    labels[40:44, 18:22, 30:34] = 9  # a small nerve, 0.6–0.9 mm below the top
    grid = BoneGrid(density, 0.1, labels=labels)
    table = MaterialTable({1: Material("cortical", 805.1, 1.3),
                           9: Material("facial nerve", 50.0, 1.0, forbidden=True)})
    engine = engine_for(grid, materials=table)
    z = 3.95 + 2.0 - 0.8  # cap 0.8 mm deep: reaches the nerve only when above it
    touches = []
    for i in range(80):
        x = 1.0 + 0.1 * i
        result = engine.step((x, 2.0, z), AXIS, (100.0, 0, 0), RPM, time_s=i * 1e-3)
        touches.append(result.forbidden_contact)
    assert any(touches) and not touches[0] and not touches[-1]
    assert len(engine.events) == 1  # one continuous contact, one event
    event = engine.events[0]
    assert event.label == 9 and event.material == "facial nerve"
    assert 3.9 <= event.position_mm[0] <= 4.4 and event.time_s == touches.index(True) * 1e-3
    # Leaving and coming back is a new contact.
    engine.step((4.2, 2.0, z), AXIS, (-100.0, 0, 0), RPM, time_s=1.0)
    assert len(engine.events) == 2


def test_adjacent_forbidden_structures_give_one_event_each():
    density = np.full((80, 40, 40), 255, np.uint8)
    labels = np.ones(density.shape, np.uint8)
    labels[40:44, 18:22, 30:34] = 9
    labels[44:48, 18:22, 30:34] = 10  # a vessel right beside the nerve
    grid = BoneGrid(density, 0.1, labels=labels)
    table = MaterialTable({1: Material("cortical", 805.1, 1.3),
                           9: Material("facial nerve", 50.0, 1.0, forbidden=True),
                           10: Material("sigmoid sinus", 20.0, 1.0, forbidden=True)})
    engine = engine_for(grid, materials=table)
    for i in range(80):
        engine.step((1.0 + 0.1 * i, 2.0, 3.95 + 2.0 - 0.8), AXIS, (100.0, 0, 0), RPM,
                    time_s=i * 1e-3)
    assert sorted(e.label for e in engine.events) == [9, 10]
    assert engine.events[0].time_s < engine.events[1].time_s


def test_forbidden_flags_changed_later_are_honoured():
    density = np.full((80, 40, 40), 255, np.uint8)
    labels = np.ones(density.shape, np.uint8)
    labels[40:44, 18:22, 30:34] = 9
    grid = BoneGrid(density, 0.1, labels=labels)
    table = MaterialTable({1: Material("cortical", 805.1, 1.3), 9: Material("nerve", 50.0, 1.0)})
    engine = engine_for(grid, materials=table)
    engine.step((1.0, 2.0, 5.15), AXIS, (100.0, 0, 0), RPM)
    table.update(9, forbidden=True)  # flagged after the engine started
    for i in range(1, 80):
        engine.step((1.0 + 0.1 * i, 2.0, 5.15), AXIS, (100.0, 0, 0), RPM)
    assert [e.label for e in engine.events] == [9]


@given(st.floats(0.0, 8.0), st.floats(0.0, 8.0), st.floats(-2.0, 3.0), st.floats(0.6, 2.5))
def test_carving_invariants(x, y, z, radius):
    grid = workpiece_block(0.2, lo_mm=(0, 0, -3), hi_mm=(8, 8, 0), margin_mm=0.5,
                           offset_voxels=(0.31, 0.17, 0.43))
    from burrforce.server.model import CuttingParams

    engine = BoneEngine(grid, params=CuttingParams(radius_mm=radius),
                        shaft=ShaftParams(length_mm=0.0), n_theta=8)
    total = grid.bone_volume_by_label_mm3()[1]
    result = engine.step((x, y, z), AXIS, (10.0, 0, 0), RPM)
    left = grid.bone_volume_by_label_mm3()[1]
    assert result.removed_mm3 >= 0.0
    assert total - left == pytest.approx(result.removed_mm3, abs=1e-9)
    assert result.removed_mm3 <= 4 / 3 * math.pi * (radius + 0.2) ** 3
    for step in range(1, 4):
        swept = grid.swept.copy()
        engine.step((x + 0.1 * step, y, z), AXIS, (10.0, 0, 0), RPM)
        assert (grid.swept >= swept).all()  # never un-carves
    bone = grid.brick_bone.copy()
    grid.recount()
    assert np.array_equal(bone, grid.brick_bone)


@given(st.lists(st.tuples(st.floats(-0.03, 0.03), st.floats(-0.03, 0.03),
                          st.floats(-0.03, 0.03)), min_size=2, max_size=6),
       st.floats(0.0, 1.0))
def test_skipping_what_the_last_tick_swept_changes_nothing(steps, depth):
    """The carve skips voxels closer to the last tick's centre than to this one: the bone it
    leaves must be what carving every covered voxel from scratch each tick leaves, up to one
    coverage quantum (a voxel's coverage is not exactly monotone in its distance from the
    burr, so the half-space can miss a 1/255 gain), and marks the same air reached but for
    air such a missed quantum would have reached (air compared as reached or not)."""
    grids = [small_block(0.2), small_block(0.2)]
    engines = [engine_for(g) for g in grids]
    centre = np.array([4.0, 4.0, 2.0 - depth])
    for step in steps:
        centre = centre + np.asarray(step)
        for n, engine in enumerate(engines):
            if n == 1:
                engine._previous[:] = np.nan  # no previous position: nothing is skipped
            engine.step(centre, AXIS, STILL, RPM)
    diff = as_the_tick_reads(grids[1]) - as_the_tick_reads(grids[0])
    assert diff.min() >= 0  # skipping never carves more
    assert diff.max() <= 1
    assert np.count_nonzero(diff) <= 8
    assert np.count_nonzero(grids[0].swept) > 0


@settings(max_examples=examples(40), deadline=None)
@given(st.lists(st.tuples(st.floats(-0.05, 0.05), st.floats(-0.05, 0.05),
                          st.floats(-0.05, 0.05)), min_size=2, max_size=8),
       st.floats(0.5, 1.5))
def test_bone_inside_where_the_burr_last_carved_is_swept_through(steps, depth):
    """What the carve's row skip rests on: every voxel of bone whose centre lies inside the
    inner sphere (wholly covered) of the burr where it last carved is swept through, however
    the rows and voxels closer to the carve before it were skipped."""
    grid = small_block(0.2)
    engine = engine_for(grid)
    centre = np.array([4.0, 4.0, 2.0 - depth])
    h = grid.spacing_mm
    idx = np.indices(grid.density.shape).reshape(3, -1).T * h
    half_diag = 0.5 * float(np.linalg.norm(h))
    r_in = engine.params.radius_mm - half_diag
    for step in steps:
        centre = centre + np.asarray(step)
        engine.step(centre, AXIS, STILL, RPM)
        last = engine._previous
        inside = np.sum((idx - last) ** 2, axis=1) < r_in * r_in * (1.0 - 1e-9)
        bone = grid.density.reshape(-1) > 0
        assert np.any(inside & bone)  # 0.5 mm deep or more: bone is inside
        assert np.all(grid.swept.reshape(-1)[inside & bone] == 255)


@pytest.mark.parametrize(("dx", "dz"), [(0.0, 5e-324), (0.0, -5e-324), (0.0, 3e-309),
                                       (0.05, 5e-324), (0.05, 1e-295), (0.05, -1e-295)])
def test_a_step_of_almost_nothing_along_z_carves_as_from_scratch(dx, dz):
    """Two carving positions a subnormal or 1e-295 mm apart in z (grid frame), with or
    without a step sideways: the skip of what the last tick swept divided by qz·hz, which
    underflowed to 0 (a ZeroDivisionError in the tick, answered INTERNAL), and a step almost
    level in z put the half-space's cut far beyond what converts to an int. It must leave
    what carving every covered voxel from scratch leaves (up to a coverage quantum, as
    ``test_skipping_what_the_last_tick_swept_changes_nothing``)."""
    axis, still = np.array(AXIS), np.zeros(3)
    grids = [small_block(), small_block()]
    engines = [engine_for(g) for g in grids]
    for n, engine in enumerate(engines):
        engine.step_raw(np.array([4.0, 4.0, 0.0]), axis, still, RPM)
        swept = engine.grid.swept.copy()
        if n == 1:
            engine._previous[:] = np.nan  # nothing skipped
        removed = engine.step_raw(np.array([4.0 + dx, 4.0, dz]), axis, still, RPM)
        if dx == 0.0:  # the burr did not move: nothing to take
            assert not removed and np.array_equal(engine.grid.swept, swept)
        else:
            assert removed
    diff = as_the_tick_reads(grids[1]) - as_the_tick_reads(grids[0])
    assert 0 <= diff.min() and diff.max() <= 1 and np.count_nonzero(diff) <= 8


#: A burr of revolution: every burr but the round abrasive one carves with its profile
#: (``carve_hooks.RevolvedCarve``).
BARREL = Burr(Barrel(1.5, 1.0, 4.0))


@pytest.mark.parametrize("burr", [None, BARREL], ids=["sphere", "barrel"])
def test_air_keeps_only_whether_a_burr_reached_it(burr):
    """Air (original density 0) is marked swept through (255) the first time a burr covers
    any of it, so the carve does not cover it again every tick the burr passes: the air
    marked is exactly the air the burr's coverage reaches in bricks that hold bone (the
    carve skips the others), and the bone is carved as in a block without air (every voxel
    bone). For the round abrasive burr's carve and for a burr of revolution's."""
    grid = small_block()
    solid = small_block()
    solid.density[:] = 255
    solid.recount()
    with_bone = grid.brick_bone > 0
    for g in (grid, solid):
        engine = engine_for(g)
        if burr is not None:
            engine.set_burr(burr)
        for x in (3.0, 3.05, 3.4):
            engine.step((x, 4.0, 1.2), AXIS, (3.0, 0.0, 0.0), RPM)
    brick_of = np.ix_(*(np.arange(n) // BRICK for n in grid.shape))
    air = (grid.density == 0) & with_bone[brick_of]
    assert not (grid.swept[(grid.density == 0) & ~with_bone[brick_of]]).any()
    assert set(np.unique(grid.swept[air]).tolist()) == {0, 255}
    assert np.array_equal(grid.swept[air] == 255, solid.swept[air] > 0)
    bone = grid.density > 0
    assert np.array_equal(grid.swept[bone], solid.swept[bone])
    carved = grid.swept[bone]
    assert ((carved > 0) & (carved < 255)).any() and (carved == 255).any()


@pytest.mark.parametrize("burr", [None, BARREL], ids=["sphere", "barrel"])
@settings(max_examples=examples(10))
@given(seed=st.integers(0, 2**32 - 1))
def test_the_tick_reads_of_air_only_whether_a_burr_reached_it(burr, seed):
    """Forces, removal and the bone's carving read of an air voxel only whether a burr has
    reached it: air reached holding any share (as a carve that tracked air's coverage left
    it) gives the same tick, bit for bit, as air marked swept through, and marks the same
    air."""
    engines = [engine_for(small_block(), n_theta=12) for _ in range(2)]
    for engine in engines:
        if burr is not None:
            engine.set_burr(burr)
        for n in range(6):  # a plunge, then a groove along x
            centre = (3.0 + 0.02 * max(n - 2, 0), 4.0, 2.0 - 0.2 * min(n, 2))
            engine.step(centre, AXIS, (20.0, 0.0, -5.0), RPM)
    g = engines[1].grid
    reached = (g.density == 0) & (g.swept > 0)
    assert reached.any()
    g.swept[reached] = np.random.default_rng(seed).integers(1, 256, np.count_nonzero(reached))
    outs = []
    for engine in engines:
        result = engine.step((3.1, 4.0, 1.6), AXIS, (20.0, 0.0, 0.0), RPM)
        grid = engine.grid
        outs.append((engine.out.copy(), result.removed_mm3,
                     np.where(grid.density > 0, grid.swept, 0),
                     (grid.density == 0) & (grid.swept > 0)))
    assert outs[0][0][0:3].any()  # a force
    assert np.array_equal(outs[0][0], outs[1][0])
    assert outs[0][1] == outs[1][1] > 0.0
    assert np.array_equal(outs[0][2], outs[1][2])
    assert np.array_equal(outs[0][3], outs[1][3])
    assert outs[0][3].sum() > reached.sum()  # this tick reached more air


@given(st.lists(st.floats(0.0, 1e9), max_size=256), st.integers(0, 2**32 - 1))
def test_the_ticks_removal_is_summed_as_numpy_sums(values, seed):
    """``removed_mm3`` (one compiled call per cutting packet) adds in numpy's pairwise order,
    so replies and recordings carry the same bits as when numpy summed the removal."""
    from burrforce.server.bone.tick import pairwise_sum, removed_mm3

    a = np.asarray(values, dtype=np.float64)
    assert pairwise_sum(a, 0, len(a)) == a.sum()
    labels = np.zeros(256)  # as a tick leaves it: a few materials removed, the rest zero
    rng = np.random.default_rng(seed)
    labels[rng.choice(256, min(len(a), 256), replace=False)] = a[:256]
    spacing = rng.uniform(0.01, 1.0, 3)
    assert removed_mm3(labels, spacing) == float(labels.sum()) * (
        float(np.prod(spacing)) / (255.0 * 255.0))
