"""The voxel grid, its bricks, materials and the workpiece phantom."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from burrforce.server.bench.accuracy import oblique_rotation
from burrforce.server.bone import BoneGrid, Material, MaterialTable, workpiece_block
from burrforce.server.bone.bricks import EMPTY, FULL, MIXED
from burrforce.server.bone.orthonormal import ROUND_OFF, gram_error, nearest_orthonormal


def test_workpiece_volume_is_exact_aligned_and_oblique():
    for direction in (None, oblique_rotation()):
        grid = workpiece_block(0.2, lo_mm=(0, 0, -3), hi_mm=(7, 5, 0),
                               offset_voxels=(0.31, 0.17, 0.43), direction=direction)
        volume = grid.bone_volume_by_label_mm3()[1]
        assert volume == pytest.approx(7 * 5 * 3, rel=1e-3)


def test_workpiece_top_face_is_at_z0():
    grid = workpiece_block(0.1, lo_mm=(0, 0, -2), hi_mm=(2, 2, 0),
                           offset_voxels=(0.0, 0.0, 0.3))
    # The voxel whose centre is nearest z = 0 straddles the face: partial volume.
    k = np.argmin(np.abs(grid.origin_mm[2] + 0.1 * np.arange(grid.shape[2])))
    column = grid.density[grid.shape[0] // 2, grid.shape[1] // 2]
    centre_z = grid.origin_mm[2] + 0.1 * k
    assert column[k] == round(255 * (0.5 - centre_z / 0.1))
    assert column[k - 3] == 255 and column[k + 3] == 0


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"hi_mm": (np.inf, 1, 1)}, "finite"), ({"label": 300}, "label"), ({"label": 0}, "label"),
    ({"hi_mm": (-1, 1, 1)}, "lo < hi"), ({"voxel_mm": 0.0}, "voxel_mm"),
])
def test_workpiece_rejects_bad_input(kwargs, message):
    args = {"voxel_mm": 0.5, "lo_mm": (0, 0, 0), "hi_mm": (1, 1, 1), **kwargs}
    with pytest.raises(ValueError, match=message):
        workpiece_block(**args)


def test_grid_frames_round_trip():
    rot = oblique_rotation()
    grid = BoneGrid(np.zeros((4, 5, 6), np.uint8), (0.1, 0.2, 0.3), origin_mm=(1, 2, 3),
                    direction=rot)
    p = np.array([0.3, -1.2, 4.5])
    assert np.allclose(grid.to_world_point(grid.to_grid_point(p)), p)
    assert np.allclose(grid.voxel_centre_mm((1, 2, 3)), (1, 2, 3) + rot @ [0.1, 0.4, 0.9])
    lo, hi = grid.bounds_mm()
    assert (lo < grid.origin_mm).all() and (hi > grid.origin_mm).all()


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"density": np.zeros((4, 4, 4), np.float32)}, "uint8"),
    ({"density": np.zeros((4, 4), np.uint8)}, "3-D"),
    ({"density": np.zeros((0, 4, 4), np.uint8)}, "empty"),
    ({"spacing_mm": 0.0}, "spacing_mm"),
    ({"spacing_mm": (0.1, 0.1)}, "one number or three"),
    ({"spacing_mm": float("nan")}, "spacing_mm"),
    ({"origin_mm": (0, float("inf"), 0)}, "origin_mm"),
    ({"direction": np.diag([1.0, 1.0, -1.0])}, "reflection"),
    ({"direction": np.diag([1.0, 2.0, 1.0])}, "orthonormal"),
    ({"labels": np.zeros((3, 3, 3), np.uint8)}, "shape"),
    ({"labels": 256}, "labels"),
])
def test_grid_rejects_bad_input(kwargs, message):
    args = {"density": np.zeros((4, 4, 4), np.uint8), "spacing_mm": 0.1, **kwargs}
    density = args.pop("density")
    spacing = args.pop("spacing_mm")
    with pytest.raises(ValueError, match=message):
        BoneGrid(density, spacing, **args)


def test_from_fraction_validates_and_rounds():
    grid = BoneGrid.from_fraction(np.full((2, 2, 2), 0.5), 0.1)
    assert (grid.density == 128).all()
    with pytest.raises(ValueError, match="within"):
        BoneGrid.from_fraction(np.full((2, 2, 2), 1.5), 0.1)


def test_brick_status_and_remaining_density():
    density = np.zeros((16, 8, 8), np.uint8)
    density[:8] = 255
    density[8, 0, 0] = 100
    grid = BoneGrid(density, 0.1)
    assert grid.brick_status().ravel().tolist() == [FULL, MIXED]
    grid.swept[:8] = 255
    grid.swept[8, 0, 0] = 51
    grid.recount()
    assert grid.brick_status().ravel().tolist() == [EMPTY, MIXED]
    assert grid.remaining_density()[8, 0, 0] == 80  # 100 · 204 / 255
    assert grid.bone_volume_by_label_mm3()[1] == pytest.approx(100 * 204 / 255**2 * 1e-3)


def test_material_table():
    table = MaterialTable()
    assert table[1].name == "cortical" and table.us[1] == pytest.approx(805.1)
    table.set(7, Material("facial nerve", 50.0, 1.0, forbidden=True))
    assert table.forbidden[7] == 1 and table.usk[7] == 50.0
    before = table.revision
    table.update(7, us_n_mm2=60.0)
    assert table.us[7] == 60.0 and table.revision > before
    with pytest.raises(ValueError, match="already label"):
        table.set(8, Material("cortical", 1.0, 1.0))
    with pytest.raises(ValueError, match="0 is empty"):
        table.set(0, Material("air", 0.0, 0.0))
    with pytest.raises(ValueError, match="us_n_mm2"):
        Material("bad", -1.0, 1.0)
    with pytest.raises(ValueError, match="us_n_mm2"):
        Material("bad", 1e308, 1.0)
    with pytest.raises(ValueError, match="k must"):
        Material("bad", 1.0, 1e3)
    with pytest.raises(ValueError, match="name"):
        Material("", 1.0, 1.0)
    table.remove(7)
    assert 7 not in table and table.us[7] == 0.0
    assert table.name_of(9) == "label 9"


# -- directions: kept bit for bit when orthonormal, snapped the same on every BLAS ------------

#: Run in a child process per OpenBLAS setting: saves and reloads an oblique grid whose
#: direction is orthonormal to round-off, and one whose direction was rounded to 7 decimals (as
#: files store it), and prints each direction's bytes after building and after reloading.
_ROUND_TRIP = """
import sys
from pathlib import Path
import numpy as np
from burrforce.server.bone import Bone, BoneGrid, MaterialTable, load_bone, save_bone
from burrforce.server.bone.materials import CORTICAL

a, b = np.radians(20.0), np.radians(-35.0)
ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
# Rz(a)·Ry(b) written out element by element: no matrix product, so no BLAS in the input.
exact = np.array([[ca * cb, -sa, ca * sb], [sa * cb, ca, sa * sb], [-sb, 0.0, cb]])
for name, direction in (("exact", exact), ("rounded", np.round(exact, 7))):
    grid = BoneGrid(np.full((3, 4, 5), 128, np.uint8), 0.2, (1.0, 2.0, 3.0), direction)
    path = save_bone(Bone(grid, MaterialTable({1: CORTICAL})), Path(sys.argv[1]) / name)
    again = load_bone(path).grid.direction
    print(name, grid.direction.tobytes().hex(), again.tobytes().hex(), direction.tobytes().hex())
"""


def _round_trip(tmp_path, coretype: str | None) -> dict[str, list[str]]:
    # The child's environment only: this process's and CI's OpenBLAS settings stay as they are.
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"}
    if coretype:
        env["OPENBLAS_CORETYPE"] = coretype
    folder = tmp_path / (coretype or "default")
    folder.mkdir()
    out = subprocess.run([sys.executable, "-c", _ROUND_TRIP, str(folder)], env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    return {line.split()[0]: line.split()[1:] for line in out.stdout.splitlines()}


def test_saved_direction_reloads_bit_for_bit_on_any_blas(tmp_path):
    """The compact format's round trip failed by 1 ulp with OPENBLAS_CORETYPE=Haswell when
    every direction was re-orthonormalised by an SVD (issue 42)."""
    runs = {coretype: _round_trip(tmp_path, coretype) for coretype in (None, "Haswell")}
    for rows in runs.values():
        built, reloaded, given = rows["exact"]
        assert built == reloaded == given  # orthonormal to round-off: kept as it is
        built, reloaded, given = rows["rounded"]
        assert built == reloaded != given  # snapped once, then kept
        snapped = np.frombuffer(bytes.fromhex(built)).reshape(3, 3)
        assert np.abs(snapped.T @ snapped - np.eye(3)).max() < 1e-14
    # The snap uses no BLAS: the same bits whichever kernel ran it.
    assert runs[None] == runs["Haswell"]


def test_nearest_orthonormal_keeps_round_off_and_snaps_the_rest():
    rot = oblique_rotation()
    assert nearest_orthonormal(rot) is rot
    rounded = np.round(rot, 4)
    snapped = nearest_orthonormal(rounded)
    assert gram_error(snapped) <= ROUND_OFF
    assert nearest_orthonormal(snapped) is snapped
    np.testing.assert_allclose(snapped, rot, atol=1e-4)
    reflected = rounded * np.array([-1.0, 1.0, 1.0])
    assert np.linalg.det(nearest_orthonormal(reflected)) == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="singular"):
        nearest_orthonormal(np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
