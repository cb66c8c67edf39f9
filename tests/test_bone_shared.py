"""A bone in shared memory: the precomputed brick summaries, and the seqlock around carving."""

from __future__ import annotations

import numpy as np
import pytest

from burrforce.server.bone import CORTICAL, NERVE, TRABECULAR, Bone, BoneEngine, BoneGrid
from burrforce.server.bone import engine as engine_module
from burrforce.server.bone import grid as grid_module
from burrforce.server.bone.bricks import (
    brick_labels,
    count_bricks,
    forbidden_bricks,
    forbidden_from_labels,
)
from burrforce.server.bone.materials import MaterialTable
from burrforce.server.bone.seqlock import (
    H_SEQ,
    header_address,
    read_begin,
    read_retry,
    write_begin,
    write_end,
)
from burrforce.server.bone.shared import SharedBone, publish


def _bone() -> Bone:
    """Three materials (a forbidden nerve), partial densities, partial edge bricks, some of
    it already swept (a restored session)."""
    rng = np.random.default_rng(7)
    shape = (37, 29, 21)  # not multiples of the 8-voxel brick
    density = np.where(rng.random(shape) < 0.6, rng.integers(1, 256, shape), 0).astype(np.uint8)
    density[:16, :, :8] = 255
    labels = np.ones(shape, dtype=np.uint8)
    labels[20:, :, :] = 2
    labels[30:33, 10:12, 5:15] = 3  # the nerve
    labels[0:2, 0:2, 20] = 3  # nerve labels on empty voxels do not count
    density[0:2, 0:2, 20] = 0
    swept = np.zeros(shape, dtype=np.uint8)
    swept[:8, :8, :8] = 255
    swept[8:10, :, :] = 100
    grid = BoneGrid(density, 0.1, origin_mm=(1.0, -2.0, 3.0), labels=labels, swept=swept)
    materials = MaterialTable({1: CORTICAL, 2: TRABECULAR, 3: NERVE})
    return Bone(grid, materials, "synthetic")


def _scanned_forbidden(grid: BoneGrid, materials: MaterialTable) -> np.ndarray:
    out = np.zeros(grid.brick_bone.shape, dtype=np.uint8)
    forbidden_bricks(grid.density, grid.labels, materials.forbidden, out)
    return out


def test_the_shared_file_carries_the_brick_summaries(tmp_path):
    bone = _bone()
    grid = bone.grid
    shared = SharedBone(publish(bone, tmp_path, "b.bone"))
    assert np.array_equal(shared.brick_bone, grid.brick_bone)
    assert np.array_equal(shared.brick_full, grid.brick_full)
    bone_, full = np.zeros_like(grid.brick_bone), np.zeros_like(grid.brick_full)
    count_bricks(grid.density, grid.swept, bone_, full)
    assert np.array_equal(shared.brick_bone, bone_) and np.array_equal(shared.brick_full, full)
    mask = np.zeros_like(shared.brick_labels)
    brick_labels(grid.density, grid.labels, mask)
    assert np.array_equal(shared.brick_labels, mask)
    # Any table's forbidden bricks from the mask are the voxel scan's.
    for table in (bone.materials, MaterialTable({1: CORTICAL, 2: NERVE}), MaterialTable()):
        out = np.full(grid.brick_bone.shape, 9, dtype=np.uint8)
        forbidden_from_labels(shared.brick_labels, table.forbidden, out)
        assert np.array_equal(out, _scanned_forbidden(grid, table))
    assert _scanned_forbidden(grid, bone.materials).any()


def test_an_engine_on_a_shared_bone_matches_one_built_the_old_way(tmp_path, monkeypatch):
    bone = _bone()
    private = BoneEngine(bone.grid, bone.materials)
    ref = publish(bone, tmp_path, "b.bone")

    def no_scan(*args):
        raise AssertionError("a pass over the voxels in the hot loop")

    # Building on the shared file scans no voxel: the summaries come from the file.
    monkeypatch.setattr(grid_module, "count_bricks", no_scan)
    monkeypatch.setattr(engine_module, "forbidden_bricks", no_scan)
    shared_bone = SharedBone(ref, writable=True).bone()
    engine = BoneEngine(shared_bone.grid, shared_bone.materials)
    engine.warm_up()
    other = MaterialTable({1: NERVE, 2: TRABECULAR})
    other_bricks = engine.forbidden_bricks_for(other)
    monkeypatch.undo()

    g, p = engine.grid, private.grid
    for name in ("brick_bone", "brick_full", "brick_voxels", "brick_version"):
        assert np.array_equal(getattr(g, name), getattr(p, name)), name
    assert np.array_equal(engine._brick_forbidden, private._brick_forbidden)
    assert np.array_equal(other_bricks, _scanned_forbidden(p, other))
    # And they cut alike: same forces, same voxels, same summaries.
    for x in np.linspace(0.5, 3.0, 12):
        centre, axis, feed = (x, 1.5, 1.8), (0.0, 0.3, 1.0), (20.0, 0.0, 0.0)
        a = engine.step(centre, axis, feed, 60_000.0, time_s=x)
        b = private.step(centre, axis, feed, 60_000.0, time_s=x)
        assert np.array_equal(a.cut.force_N, b.cut.force_N)
        assert a.removed_mm3 == b.removed_mm3 and a.bone_version == b.bone_version
    assert engine.ticks and g.version > 0
    for name in ("swept", "brick_bone", "brick_full", "brick_version"):
        assert np.array_equal(getattr(g, name), getattr(p, name)), name


def test_a_session_built_from_the_shared_file_matches_the_old_way(tmp_path):
    from burrforce.server.hotloop.spec import SessionSpec, build_session

    bone = _bone()
    private = BoneEngine(bone.grid, bone.materials)
    session = build_session(SessionSpec(5, publish(bone, tmp_path, "b.bone"),
                                        materials=bone.materials))
    g = session.engine.grid
    assert g.shared_header is not None and g.brick_labels is not None
    for name in ("brick_bone", "brick_full", "brick_voxels"):
        assert np.array_equal(getattr(g, name), getattr(private.grid, name)), name
    assert np.array_equal(session.engine._brick_forbidden, private._brick_forbidden)


def test_readers_see_whole_carving_ticks(tmp_path):
    bone = _bone()
    ref = publish(bone, tmp_path, "b.bone")
    engine = BoneEngine(SharedBone(ref, writable=True).bone().grid, bone.materials)
    reader = SharedBone(ref)
    for x in np.linspace(0.5, 3.0, 6):
        engine.step((x, 1.5, 1.8), (0.0, 0.0, 1.0), (20.0, 0.0, 0.0), 60_000.0)
    assert int(reader.header[H_SEQ]) % 2 == 0 and int(reader.header[H_SEQ]) > 0
    swept, version = reader.consistent_swept()
    assert version == engine.grid.version == reader.version > 0
    assert np.array_equal(swept, engine.grid.swept)
    snapshot = reader.snapshot()
    assert np.array_equal(snapshot.grid.brick_bone, engine.grid.brick_bone)


def test_a_tick_that_raises_still_closes_the_seqlock(tmp_path):
    """An exception inside the tick (the loop answers it INTERNAL and goes on) must not leave
    the counter odd: every reader of the shared bone would retry for good."""
    bone = _bone()
    ref = publish(bone, tmp_path, "b.bone")
    engine = BoneEngine(SharedBone(ref, writable=True).bone().grid, bone.materials)
    reader = SharedBone(ref)
    engine.step((1.0, 1.5, 1.8), (0.0, 0.0, 1.0), (20.0, 0.0, 0.0), 60_000.0)
    before, version_before = int(reader.header[H_SEQ]), engine.grid.version
    # The tick cannot write its result: numba refuses it when it types the buffers, which the
    # engine does once and again only when it rebinds them.
    engine.out.flags.writeable = False
    engine._bound = None
    with pytest.raises(Exception, match="readonly"):
        engine.step((1.2, 1.5, 1.8), (0.0, 0.0, 1.0), (20.0, 0.0, 0.0), 60_000.0)
    assert int(reader.header[H_SEQ]) == before + 2
    # Under a new version: a tick that raised may have stamped bricks with it already.
    swept, version = reader.consistent_swept()
    assert version == engine.grid.version == version_before + 1
    assert np.array_equal(swept, engine.grid.swept)


def test_seqlock_counter():
    header = np.zeros(8, dtype=np.int64)
    seq = read_begin(header)
    write_begin(header_address(header))
    assert read_begin(header) == 1 and read_retry(header, seq)
    write_end(header_address(header), 42)
    assert read_begin(header) == 2 and header[1] == 42
    assert not read_retry(header, 2)
    readonly = header.copy()
    readonly.flags.writeable = False
    assert read_begin(readonly) == 2 and not read_retry(readonly, 2)


@pytest.mark.parametrize("writable", [False, True])
def test_a_file_of_the_old_layout_is_refused(tmp_path, writable):
    ref = publish(_bone(), tmp_path, "b.bone")
    with open(ref.path, "r+b") as f:
        f.seek(16)
        f.write((0x6275727266726331).to_bytes(8, "little"))  # "burrfrc1"
    with pytest.raises(ValueError, match="not a shared bone"):
        SharedBone(ref, writable=writable)
