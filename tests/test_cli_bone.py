"""``burrforce bone info`` and ``burrforce bone convert`` as a user runs them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from burrforce.server.bench import bone_files
from burrforce.server.bone.bone import Bone
from burrforce.server.bone.materials import CORTICAL, NERVE, TRABECULAR, MaterialTable
from burrforce.server.bone.phantoms import workpiece_block
from burrforce.server.cli import main

INFO_KEYS = {"shape", "spacing_mm", "origin_mm", "materials"}


@pytest.fixture(scope="module")
def bone() -> Bone:
    grid = workpiece_block(0.5)
    idx = np.indices(grid.shape)
    labels = np.where(idx[2] < grid.shape[2] // 2, np.uint8(2), np.uint8(1))
    labels[idx[0] == grid.shape[0] // 2] = 3
    grid.labels[...] = np.where(grid.density > 0, labels, 0)
    return Bone(grid, MaterialTable({1: CORTICAL, 2: TRABECULAR, 3: NERVE}), name="cli bone")


@pytest.fixture(scope="module")
def files(bone, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("files")
    return {
        "nrrd": bone_files.write_nrrd_labels(bone, root / "b.nrrd"),
        "seg.nrrd": bone_files.write_seg_nrrd(bone, root / "b.seg.nrrd"),
        "nifti": bone_files.write_nifti_ct(bone, root / "ct.nii.gz"),
        "dicom": bone_files.write_dicom_ct(bone, root / "dicom"),
        "npz": bone_files.write_npz(bone, root / "b.npz"),
        "npy": bone_files.write_npy(bone, root / "b.npy"),
        "png": bone_files.write_png_stack(bone, root / "png"),
    }


@pytest.mark.parametrize("fmt", ["nrrd", "seg.nrrd", "nifti", "dicom", "npz", "npy", "png"])
def test_bone_info_json_answers_for_every_format(fmt, files, capsys):
    extra = ["--spacing-mm", "0.5"] if fmt in ("npy", "png") else []
    assert main(["bone", "info", str(files[fmt]), "--json", *extra]) == 0
    info = json.loads(capsys.readouterr().out)
    assert INFO_KEYS <= set(info)
    assert len(info["shape"]) == 3 and len(info["spacing_mm"]) == 3
    assert info["spacing_mm"] == pytest.approx([0.5, 0.5, 0.5])
    assert sum(info["materials"].values()) > 100.0
    assert all(isinstance(v, float) for v in info["materials"].values())


def test_bone_info_table_names_the_materials(files, capsys):
    assert main(["bone", "info", str(files["nifti"])]) == 0
    out = capsys.readouterr().out
    assert "cortical" in out and "trabecular" in out and "read as ct" in out
    assert "converted from RAS to LPS" in out


def test_bone_convert_then_info(files, tmp_path, capsys):
    materials = tmp_path / "m.toml"
    materials.write_text("[materials.nerve]\nsegments = ['nerve']\n"
                         "[materials.cortical]\nsegments = ['cortical']\n"
                         "[materials.trabecular]\nsegments = ['trabecular']\n")
    out = tmp_path / "converted"
    assert main(["bone", "convert", str(files["seg.nrrd"]), str(out),
                 "--materials", str(materials)]) == 0
    assert "converted.bone.npz" in capsys.readouterr().out
    assert main(["bone", "info", str(tmp_path / "converted.bone.npz"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["format"] == "bone"
    assert set(info["materials"]) == {"cortical", "trabecular", "nerve"}
    assert [m["forbidden"] for m in info["material_table"] if m["name"] == "nerve"] == [True]


def test_bone_errors_name_the_file(files, tmp_path, capsys):
    broken = tmp_path / "broken.nii.gz"
    broken.write_bytes(files["nifti"].read_bytes()[:300])
    assert main(["bone", "info", str(broken)]) == 2
    err = capsys.readouterr().err
    assert "broken.nii.gz" in err and "error" in err
    assert main(["bone", "info", str(files["npy"])]) == 2
    assert "--spacing-mm" in capsys.readouterr().err
    bad_map = tmp_path / "bad.toml"
    bad_map.write_text("[materials.x]\n")
    assert main(["bone", "info", str(files["nrrd"]), "--materials", str(bad_map)]) == 2
    assert "bad.toml" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bone", "info", str(files["nrrd"]), "--spacing-mm", "1,2"])


def test_bone_convert_makes_the_output_folder(tmp_path, capsys):
    out = tmp_path / "new" / "folder" / "workpiece"
    assert main(["bone", "convert", "phantom:workpiece", str(out), "--voxel-mm", "1"]) == 0
    assert (out.parent / "workpiece.bone.npz").is_file()
    assert "workpiece.bone.npz" in capsys.readouterr().out


def test_file_options_on_a_phantom_are_an_error(tmp_path, capsys):
    materials = tmp_path / "m.toml"
    materials.write_text("[materials.cortical]\nlabels = [1]\n")
    assert main(["bone", "info", "phantom:temporal", "--materials", str(materials)]) == 2
    err = capsys.readouterr().err
    assert "--materials" in err and "phantom" in err
