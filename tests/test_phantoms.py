"""Phantoms: analytic volumes per material, convergence, the temporal bone's anatomy, the
registry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.bone.phantoms import (
    NERVE_CANAL_WALL_MM,
    NERVE_DEPTH_MM,
    NERVE_LABEL,
    NERVE_RADIUS_MM,
    PHANTOMS,
    TEMPORAL_AIR_CELLS_MM,
    TEMPORAL_CORTEX_MM,
    TEMPORAL_MARGIN_MM,
    TEMPORAL_SEMI_AXES_MM,
    TRABECULAR_LABEL,
    layered_block,
    layered_block_volumes_mm3,
    nerve_points_mm,
    phantom,
    temporal_bone,
    temporal_bone_volumes_mm3,
    workpiece_block,
)

CORTICAL_LABEL = 1


@pytest.fixture(scope="module")
def temporal():
    return phantom("temporal")


def relative_errors(bone, reference: dict[str, float]) -> dict[str, float]:
    volumes = bone.volumes_mm3()
    assert set(volumes) == set(reference)
    return {name: abs(volumes[name] / reference[name] - 1.0) for name in reference}


def centres_mm(grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World voxel centres of a world-aligned grid, as three broadcastable axes (mm)."""
    assert grid.identity_direction
    x, y, z = (grid.origin_mm[a] + grid.spacing_mm[a] * np.arange(grid.shape[a])
               for a in range(3))
    return x[:, None, None], y[None, :, None], z[None, None, :]


def distance_to_nerve_mm(points: np.ndarray) -> np.ndarray:
    """Distance (n,) from points (n, 3) to the nerve's centre line, from 201 samples of it
    (chords 0.09 mm long: within 1e-4 mm of the arc) — independent of the kernel's formula."""
    line = nerve_points_mm(201)
    out = np.full(len(points), np.inf)
    for start in range(0, len(points), 2048):
        chunk = points[start:start + 2048]
        out[start:start + 2048] = np.sqrt(
            ((chunk[:, None, :] - line[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
    return out


# -- volumes -------------------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "reference", "tolerance"), [
    ("workpiece", {"cortical": 26.0 * 16.0 * 8.0}, 1e-6),
    ("layered", layered_block_volumes_mm3(), 5e-3),
    ("temporal", temporal_bone_volumes_mm3(), 1e-2),
])
def test_default_phantoms_match_analytic_volumes(name, reference, tolerance, temporal):
    bone = temporal if name == "temporal" else phantom(name)
    assert max(relative_errors(bone, reference).values()) < tolerance


def test_layered_block_split_converges():
    # Core faces inside voxels (not on their faces): the label split errs, and halves with h.
    offset = (0.3, 0.1, 0.7)
    reference = layered_block_volumes_mm3()
    coarse = relative_errors(layered_block(0.2, offset_voxels=offset), reference)
    fine = relative_errors(layered_block(0.1, offset_voxels=offset), reference)
    for name in reference:
        assert fine[name] < 0.5 * coarse[name] + 1e-6
        assert fine[name] < 5e-3


def test_temporal_bone_converges(temporal):
    reference = temporal_bone_volumes_mm3()
    total = sum(reference.values())
    coarse = relative_errors(temporal_bone(0.4), reference)
    default = relative_errors(temporal, reference)
    for name in reference:
        assert default[name] < coarse[name]
    # Below 0.2 mm the label split is at its noise floor; the bone itself keeps converging.
    fine = temporal_bone(0.1)
    assert max(relative_errors(fine, reference).values()) < 5e-4
    assert abs(sum(fine.volumes_mm3().values()) - total) \
        < abs(sum(temporal.volumes_mm3().values()) - total)


def test_temporal_regions_are_nested_as_the_volumes_assume():
    """Air cells and the canal inside the trabecular interior and apart, so the analytic
    volumes add up."""
    a, b, c = (s - TEMPORAL_CORTEX_MM for s in TEMPORAL_SEMI_AXES_MM)
    directions = np.random.default_rng(0).normal(size=(4000, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]

    def inside_interior(points, clearance_mm):
        shrunk = ((points[:, 0] / (a - clearance_mm)) ** 2 + (points[:, 1] / (b - clearance_mm))
                  ** 2 + (points[:, 2] / (c - clearance_mm)) ** 2)
        return bool((shrunk < 1.0).all()
                    and (points[:, 2] < -TEMPORAL_CORTEX_MM - clearance_mm).all())

    canal_mm = NERVE_RADIUS_MM + NERVE_CANAL_WALL_MM
    canal_surface = (nerve_points_mm(101)[:, None, :]
                     + canal_mm * directions[None, ::40, :]).reshape(-1, 3)
    assert inside_interior(canal_surface, 1.0)
    cells = np.array(TEMPORAL_AIR_CELLS_MM)
    assert (1.0 <= cells[:, 3]).all() and (cells[:, 3] <= 3.0).all()
    for x, y, z, r in cells:
        assert inside_interior(np.array([x, y, z]) + r * directions, 0.5)
        assert distance_to_nerve_mm(np.array([[x, y, z]]))[0] > r + canal_mm + 1.0
    gaps = (np.linalg.norm(cells[:, None, :3] - cells[None, :, :3], axis=2)
            - cells[:, None, 3] - cells[None, :, 3])
    assert (gaps[~np.eye(len(cells), dtype=bool)] > 1.0).all()


# -- the temporal bone's anatomy -----------------------------------------------------------------
def test_temporal_top_surface_is_z0_and_body_centred(temporal):
    grid = temporal.grid
    h = grid.spacing_mm[0]
    x, y, z = centres_mm(grid)
    bone = grid.density > 0
    top = z[0, 0, np.flatnonzero(bone.any(axis=(0, 1)))[-1]] + 0.5 * h
    assert top == pytest.approx(0.0, abs=1e-9)
    a, b, c = TEMPORAL_SEMI_AXES_MM
    i, j, k = np.nonzero(bone)
    assert x.ravel()[i].min() == pytest.approx(-x.ravel()[i].max())
    assert y.ravel()[j].min() == pytest.approx(-y.ravel()[j].max())
    assert x.ravel()[i].max() == pytest.approx(a, abs=h)
    assert z.ravel()[k].min() == pytest.approx(-c, abs=h)
    lo, hi = grid.bounds_mm()
    margin = TEMPORAL_MARGIN_MM - 1e-9
    assert (lo <= np.array([-a, -b, -c]) - margin).all()
    assert (hi >= np.array([a, b, 0.0]) + margin).all()
    # The top plate is cortical, 1.6 mm (8 voxels) thick, over trabecular bone.
    column = grid.labels[grid.shape[0] // 2 - 20, grid.shape[1] // 2 + 40]
    under_top = np.flatnonzero(column)[::-1]
    plate = round(TEMPORAL_CORTEX_MM / h)
    assert (column[under_top[:plate]] == CORTICAL_LABEL).all()
    assert column[under_top[plate]] == TRABECULAR_LABEL


def test_nerve_is_forbidden_enclosed_and_at_depth(temporal):
    grid = temporal.grid
    assert temporal.materials[NERVE_LABEL].forbidden
    assert not temporal.materials[CORTICAL_LABEL].forbidden
    nerve = grid.labels == NERVE_LABEL
    assert (grid.density[nerve] == 255).all()
    # Every 26-neighbour of a nerve voxel is bone, and nerve or cortical canal wall.
    padded = np.pad(grid.labels, 1)
    dense = np.pad(grid.density, 1)
    i, j, k = np.nonzero(nerve)
    for di in (0, 1, 2):
        for dj in (0, 1, 2):
            for dk in (0, 1, 2):
                assert (dense[i + di, j + dj, k + dk] > 0).all()
                assert np.isin(padded[i + di, j + dj, k + dk],
                               (NERVE_LABEL, CORTICAL_LABEL)).all()
    depth = -centres_mm(grid)[2].ravel()[k]
    shallow, deep = NERVE_DEPTH_MM
    assert depth.min() >= shallow - NERVE_RADIUS_MM - 1e-9
    assert depth.max() <= deep + NERVE_RADIUS_MM + 1e-9
    assert -nerve_points_mm()[[0, -1], 2] == pytest.approx([shallow, deep][::-1])
    assert 5.0 <= shallow - NERVE_RADIUS_MM and deep + NERVE_RADIUS_MM <= 8.0


def test_nerve_tube_and_canal_wall_by_distance(temporal):
    grid = temporal.grid
    h = grid.spacing_mm[0]
    half_diag = 0.5 * math.sqrt(3.0) * h
    x, y, z = centres_mm(grid)
    # The voxels near the nerve: its bounding box plus the canal.
    line = nerve_points_mm()
    reach = NERVE_RADIUS_MM + NERVE_CANAL_WALL_MM + h
    near = [(c >= line[:, a].min() - reach) & (c <= line[:, a].max() + reach)
            for a, c in enumerate((x.ravel(), y.ravel(), z.ravel()))]
    i, j, k = np.ix_(*(np.flatnonzero(m) for m in near))
    i, j, k = (np.broadcast_to(v, np.broadcast_shapes(i.shape, j.shape, k.shape)).ravel()
               for v in (i, j, k))
    points = np.stack([x.ravel()[i], y.ravel()[j], z.ravel()[k]], axis=1)
    d = distance_to_nerve_mm(points)
    labels = grid.labels[i, j, k]
    density = grid.density[i, j, k]
    assert (labels[d < NERVE_RADIUS_MM - half_diag] == NERVE_LABEL).all()
    assert (labels[d > NERVE_RADIUS_MM + half_diag] != NERVE_LABEL).all()
    wall = (d > NERVE_RADIUS_MM + half_diag) \
        & (d < NERVE_RADIUS_MM + NERVE_CANAL_WALL_MM - half_diag)
    assert wall.sum() > 1000
    assert (labels[wall] == CORTICAL_LABEL).all() and (density[wall] == 255).all()


def test_air_cells_are_empty_inside_trabecular_bone(temporal):
    grid = temporal.grid
    half_diag = 0.5 * math.sqrt(3.0) * grid.spacing_mm[0]
    x, y, z = centres_mm(grid)
    for cx, cy, cz, r in TEMPORAL_AIR_CELLS_MM:
        d = np.sqrt((x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2)
        inside = d < r - half_diag
        assert inside.sum() > 100
        assert (grid.density[inside] == 0).all() and (grid.labels[inside] == 0).all()
        around = (d > r + half_diag) & (d < r + 0.5)
        assert (grid.labels[around] == TRABECULAR_LABEL).all()
        assert (grid.density[around] == 255).all()


# -- the layered block ---------------------------------------------------------------------------
@given(shell_mm=st.floats(0.05, 1.45),
       offset=st.tuples(*[st.floats(-1.0, 1.0)] * 3))
def test_layered_block_is_the_workpiece_split_in_two(shell_mm, offset):
    args = {"voxel_mm": 0.25, "lo_mm": (0.0, 0.0, -3.0), "hi_mm": (5.0, 4.0, 0.0),
            "margin_mm": 0.5, "offset_voxels": offset}
    bone = layered_block(shell_mm=shell_mm, **args)
    plain = workpiece_block(**args)
    assert np.array_equal(bone.grid.density, plain.density)
    assert (bone.grid.labels[plain.density == 0] == 0).all()
    assert np.isin(bone.grid.labels[plain.density > 0], (1, 2)).all()
    volumes = bone.volumes_mm3()
    reference = layered_block_volumes_mm3(shell_mm, args["lo_mm"], args["hi_mm"])
    block = 5.0 * 4.0 * 3.0
    assert sum(volumes.values()) == pytest.approx(block, rel=1e-3)
    # The split errs by at most half a voxel in each voxel the core's surface crosses.
    core_voxels = (np.array([5.0, 4.0, 3.0]) - 2.0 * shell_mm) / 0.25
    crossed = np.prod(core_voxels + 2.0) - np.prod(np.maximum(core_voxels - 2.0, 0.0))
    slack = 0.5 * 0.25 ** 3 * crossed + 1e-3 * block
    assert abs(volumes["trabecular"] - reference["trabecular"]) <= slack


@pytest.mark.parametrize("shell_mm", [0.0, -1.0, 4.0, 5.0, float("nan"), True, "1"])
def test_layered_block_rejects_bad_shell(shell_mm):
    with pytest.raises(ValueError, match="shell_mm"):
        layered_block(1.0, shell_mm=shell_mm)


# -- the registry --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["workpiece", "layered", "temporal"])
def test_registry_builds_each_phantom(name):
    assert set(PHANTOMS) == {"workpiece", "layered", "temporal"}
    assert all(isinstance(text, str) and "\n" not in text for text in PHANTOMS.values())
    bone = phantom(name, 0.5)
    assert (bone.name, bone.format, bone.kind) == (name, "phantom", "density")
    assert bone.grid.spacing_mm.tolist() == [0.5] * 3
    expected = {"workpiece": {1}, "layered": {1, 2}, "temporal": {1, 2, 3}}[name]
    assert set(bone.materials.labels()) == expected
    assert set(np.unique(bone.grid.labels)) - {0} <= expected
    assert bone.info()["frame"] == "phantom"


def test_registry_default_voxel_sizes(temporal):
    assert temporal.grid.spacing_mm.tolist() == [0.2] * 3
    assert phantom("workpiece").grid.spacing_mm.tolist() == [0.1] * 3


def test_registry_rejects_unknown_names():
    for name in ("skull", "", None, 3):
        with pytest.raises(ValueError, match="workpiece, layered, temporal"):
            phantom(name)


@pytest.mark.parametrize("voxel_mm", [0.0, -0.2, 11.0, float("nan"), float("inf"), True, "0.2"])
@pytest.mark.parametrize("name", ["workpiece", "temporal"])
def test_registry_rejects_bad_voxel_sizes(name, voxel_mm):
    with pytest.raises(ValueError, match="voxel_mm"):
        phantom(name, voxel_mm)


@pytest.mark.parametrize("name", ["workpiece", "layered", "temporal"])
def test_registry_refuses_too_many_voxels(name):
    with pytest.raises(ValueError, match="too large"):
        phantom(name, 0.01)
