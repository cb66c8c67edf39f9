"""The carving's tally (removal per label, forbidden contacts): exact, kept in a shared bone's
file so that an engine built again on it (a restarted hot loop) counts on, and rebuilt from a
replayed carving as the kernels count it."""

from __future__ import annotations

import numpy as np
import pytest

from burrforce.server.bone import BoneEngine, ShaftParams, phantom
from burrforce.server.bone.shared import SharedBone, brick_blocks, publish
from burrforce.server.bone.tally import CarveTally, removal_of
from burrforce.server.model.params import CuttingParams

AXIS = np.array([0.0, 0.0, 1.0])
FEED = np.array([5.0, 0.0, 0.0])


def _engine(shared: SharedBone) -> BoneEngine:
    bone = shared.bone()
    return BoneEngine(bone.grid, bone.materials, CuttingParams(), ShaftParams(length_mm=0.0),
                      tally=shared.tally)


def _groove(engine: BoneEngine, start_mm: float, z_mm: float, n: int) -> None:
    grid = engine.grid
    for i in range(n):
        centre = grid.to_grid_point(np.array([start_mm + 0.01 * i, 0.0, z_mm]))
        engine.step_raw(centre, AXIS, FEED, 60000.0, True)
        engine.record_contact(float(i))


def _true_units(shared: SharedBone) -> np.ndarray:
    """Σ density × swept per label: the removal of a bone loaded uncarved."""
    d = shared.density.astype(np.float64) * shared.swept
    return np.bincount(shared.labels.ravel(), weights=d.ravel(), minlength=256)


def test_a_private_ring_grows_wraps_and_loads_back():
    tally = CarveTally.private(100)
    for i in range(250):
        tally.add_contact(float(i), (1.0, 2.0, 3.0), 9)
    assert tally.begun == 250
    kept = tally.latest(None, str)
    assert [c.time_s for c in kept] == [float(i) for i in range(150, 250)]
    assert kept[0].material == "9" and kept[0].position_mm == (1.0, 2.0, 3.0)
    first, rows = tally.rows_since(240)
    assert first == 240 and rows[:, 0].tolist() == [float(i) for i in range(240, 250)]
    copy = CarveTally.private()
    copy.load(np.arange(256.0), 250, *tally.rows_since(0))
    assert copy.begun == 250 and copy.latest(3, str) == tally.latest(3, str)
    assert copy.removed[7] == 7.0
    unbounded = CarveTally.private(1 << 30)  # a replay asks for no limit: nothing allocated
    unbounded.add_contact(0.0, (0.0, 0.0, 0.0), 1)
    assert unbounded.begun == 1


def test_an_engine_built_again_on_the_shared_bone_counts_on(tmp_path):
    """What a hot-loop restart does: the killed loop's engine is gone, the new one maps the
    same file. Its removal and contacts go on from the old totals, and equal the bone's."""
    bone = phantom("layered", 0.25)
    bone.materials.update(2, forbidden=True)  # the trabecular core
    ref = publish(bone, tmp_path, "b.bone")
    first = _engine(SharedBone(ref, writable=True))
    _groove(first, 2.0, -1.0, 150)  # deep: into the forbidden core
    before = first.removed_mm3_by_material()
    begun = first.tally.begun
    assert before and begun >= 1
    del first
    shared = SharedBone(ref, writable=True)
    second = _engine(shared)
    assert second.removed_mm3_by_material() == before
    assert second.tally.begun == begun and len(second.events) == begun
    _groove(second, 2.0, 1.0, 150)  # out of the core (the contact ends), then into it again
    _groove(second, 4.0, -1.0, 150)
    assert second.tally.begun > begun
    units = _true_units(shared)
    assert np.array_equal(second.tally.removed, units)  # exact: integral sums
    reader = SharedBone(ref)  # the control plane's read-only map sees the same
    assert np.array_equal(reader.tally.removed, units)
    assert reader.tally.begun == second.tally.begun
    by_material = second.removed_mm3_by_material()
    assert sum(by_material.values()) == pytest.approx(
        units.sum() * bone.grid.voxel_volume_mm3 / 255 ** 2, rel=1e-12)


def test_a_published_tally_and_the_replayed_removal(tmp_path):
    """A resumed session's bone is shared with the tally its journal kept; the removal a
    replayed carving adds is what the kernels counted while cutting it."""
    cut = phantom("workpiece", 0.2)
    engine = BoneEngine(cut.grid, cut.materials, CuttingParams(), ShaftParams(length_mm=0.0))
    _groove(engine, 3.0, -0.6, 300)
    index = np.argwhere(cut.grid.brick_version > 0)
    fresh = phantom("workpiece", 0.2)
    units = removal_of(fresh.grid, index, brick_blocks(cut.grid.swept, index))
    assert np.array_equal(units, engine.tally.removed)
    tally = CarveTally.private()
    tally.load(units, 3, 0, np.arange(15.0).reshape(3, 5))
    shared = SharedBone(publish(fresh, tmp_path, "r.bone", tally))
    assert np.array_equal(shared.tally.removed, units) and shared.tally.begun == 3
    assert [c.label for c in shared.tally.latest(None, str)] == [4, 9, 14]


def test_carving_since_takes_bricks_and_removal_together(tmp_path):
    bone = phantom("workpiece", 0.2)
    ref = publish(bone, tmp_path, "c.bone")
    shared = SharedBone(ref, writable=True)
    engine = _engine(shared)
    _groove(engine, 3.0, -0.6, 200)
    reader = SharedBone(ref)
    take = reader.carving_since(0)
    assert len(take.index) and take.bone_version == engine.grid.version
    assert np.array_equal(take.removed, engine.tally.removed)
    fresh = phantom("workpiece", 0.2)
    assert np.array_equal(removal_of(fresh.grid, take.index, take.blocks), take.removed)
    later = reader.carving_since(take.bone_version)
    assert len(later.index) == 0
