"""Bone files in every format: written by the format's own library, read back by ours."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from burrforce.server.bench import bone_files
from burrforce.server.bone.bone import Bone
from burrforce.server.bone.loaders import (
    BoneFileError,
    LoadOptions,
    detect_format,
    load_bone,
    save_bone,
)
from burrforce.server.bone.material_map import MaterialMap
from burrforce.server.bone.materials import CORTICAL, NERVE, TRABECULAR, MaterialTable
from burrforce.server.bone.phantoms import phantom, workpiece_block

VOXEL_MM = 0.4


@pytest.fixture(scope="module")
def bone() -> Bone:
    """A three-material bone on an oblique grid: the workpiece block, trabecular below
    z = −2 mm, a nerve box inside; partial volume at every face."""
    rot = _rotation((12.0, -7.0, 25.0))
    grid = workpiece_block(VOXEL_MM, direction=rot, offset_voxels=(0.3, -0.2, 0.1))
    nx, ny, nz = grid.shape
    idx = np.indices(grid.shape).reshape(3, -1).T * grid.spacing_mm
    world = (grid.origin_mm + idx @ grid.direction.T).reshape(nx, ny, nz, 3)
    labels = np.where(world[..., 2] < -2.0, np.uint8(2), np.uint8(1))
    nerve = (np.abs(world[..., 0] - 13) < 8) & (np.abs(world[..., 1]) < 1.0) \
        & (np.abs(world[..., 2] + 5) < 1.0)
    labels[nerve] = 3
    grid.labels[...] = np.where(grid.density > 0, labels, 0)
    grid.recount()
    return Bone(grid, MaterialTable({1: CORTICAL, 2: TRABECULAR, 3: NERVE}), name="test bone")


@pytest.fixture(scope="module")
def materials_file(bone, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("map") / "materials.toml"
    path.write_text(bone_files.materials_toml(bone))
    return path


def _rotation(euler_deg) -> np.ndarray:
    rot = np.eye(3)
    for axis, deg in enumerate(euler_deg):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        r = np.eye(3)
        a, b = [(1, 2), (2, 0), (0, 1)][axis]
        r[a, a] = r[b, b] = c
        r[a, b], r[b, a] = -s, s
        rot = r @ rot
    return rot


def _label_volumes(bone: Bone) -> dict[str, float]:
    """Volumes of the bone written as a label map (the voxels at least half bone)."""
    labels = bone_files.label_map(bone)
    return {m.name: float(np.count_nonzero(labels == label)) * bone.grid.voxel_volume_mm3
            for label, m in bone.materials}


def _assert_volumes(loaded: dict[str, float], expected: dict[str, float], rel: float) -> None:
    for name, volume in expected.items():
        assert loaded.get(name, 0.0) == pytest.approx(volume, rel=rel), (name, loaded, expected)
    assert set(loaded) <= set(expected) | {n for n, v in loaded.items() if v == 0.0}


def _assert_geometry(loaded: Bone, bone: Bone) -> None:
    """Same voxels in the same places (an axis may be stored flipped)."""
    np.testing.assert_allclose(loaded.grid.spacing_mm, bone.grid.spacing_mm, rtol=1e-6)
    lo, hi = loaded.grid.bounds_mm()
    lo0, hi0 = bone.grid.bounds_mm()
    np.testing.assert_allclose(lo, lo0, atol=1e-4)
    np.testing.assert_allclose(hi, hi0, atol=1e-4)
    centre = np.array(bone.grid.shape) // 2
    world = bone.grid.voxel_centre_mm(tuple(centre))
    back = loaded.grid.to_grid_point(world) / loaded.grid.spacing_mm
    np.testing.assert_allclose(back, np.rint(back), atol=1e-4)


# -- round trips --------------------------------------------------------------------------
LABEL_WRITERS = {
    "nrrd labels": (bone_files.write_nrrd_labels, "bone.nrrd", "labels"),
    "seg.nrrd": (bone_files.write_seg_nrrd, "bone.seg.nrrd", "labels"),
    "seg.nrrd layered": (lambda b, p: bone_files.write_seg_nrrd(b, p, layered=True),
                         "layers.seg.nrrd", "labels"),
    "nifti labels": (bone_files.write_nifti_labels, "bone.nii.gz", "labels"),
    "png rgba": (bone_files.write_png_stack, "planes", "density"),
}


@pytest.mark.parametrize("name", list(LABEL_WRITERS))
def test_label_formats_round_trip(name, bone, materials_file, tmp_path):
    writer, filename, kind = LABEL_WRITERS[name]
    path = writer(bone, tmp_path / filename)
    spacing = tuple(bone.grid.spacing_mm) if name.startswith("png") else None
    options = LoadOptions(materials=MaterialMap.from_file(materials_file), spacing_mm=spacing)
    loaded = load_bone(path, options)
    assert loaded.kind == kind
    # NIfTI stores its affine in float32.
    _assert_volumes(loaded.volumes_mm3(), _label_volumes(bone),
                    rel=1e-6 if "nifti" in name else 1e-9)
    if not name.startswith("png"):  # a PNG stack has no geometry
        _assert_geometry(loaded, bone)
    assert loaded.materials[loaded.materials.label_of("nerve")].forbidden


@pytest.mark.parametrize("writer,filename", [(bone_files.write_nrrd_ct, "ct.nrrd"),
                                             (bone_files.write_nifti_ct, "ct.nii"),
                                             (bone_files.write_dicom_ct, "dicom")])
def test_ct_formats_round_trip(writer, filename, bone, tmp_path):
    path = writer(bone, tmp_path / filename)
    loaded = load_bone(path)  # default HU presets: trabecular 148–661, cortical 662–1988
    assert loaded.kind == "ct"
    expected = _label_volumes(bone)
    del expected["nerve"]  # soft tissue: not bone in a CT
    _assert_volumes(loaded.volumes_mm3(), expected, rel=1e-6)
    _assert_geometry(loaded, bone)


def test_density_formats_keep_partial_volume(bone, materials_file, tmp_path):
    expected = bone.volumes_mm3()
    npz = load_bone(bone_files.write_npz(bone, tmp_path / "bone.npz"),
                    LoadOptions(materials=MaterialMap.from_file(materials_file)))
    _assert_volumes(npz.volumes_mm3(), expected, rel=1e-9)
    _assert_geometry(npz, bone)
    total = sum(expected.values())
    npy = load_bone(bone_files.write_npy(bone, tmp_path / "bone.npy"),
                    LoadOptions(spacing_mm=(VOXEL_MM,) * 3))
    assert npy.kind == "density"
    assert npy.volumes_mm3() == {"cortical": pytest.approx(total, rel=1e-9)}
    gray = load_bone(bone_files.write_png_gray(bone, tmp_path / "gray"),
                     LoadOptions(spacing_mm=(VOXEL_MM,) * 3, kind="density"))
    assert gray.volumes_mm3() == {"cortical": pytest.approx(total, rel=1e-9)}


def test_compact_format_round_trips_everything(bone, tmp_path):
    bone.grid.swept[5:9, 5:9, :] = 200  # a carved session
    try:
        path = save_bone(bone, tmp_path / "session")
        assert path.name == "session.bone.npz"
        loaded = load_bone(path)
        for name in ("density", "labels", "swept", "spacing_mm", "origin_mm", "direction"):
            np.testing.assert_array_equal(getattr(loaded.grid, name), getattr(bone.grid, name))
        assert dict(loaded.materials) == dict(bone.materials)
        assert loaded.volumes_mm3() == pytest.approx(bone.volumes_mm3(), rel=1e-12)
        assert loaded.format == "bone"
        # Plain NumPy reads it too.
        with np.load(path) as npz:
            assert npz["density"].shape == bone.grid.shape
        assert path.stat().st_size < bone.grid.density.nbytes  # compressed
    finally:
        bone.grid.swept[...] = 0


@pytest.fixture(scope="module")
def temporal():
    return phantom("temporal", 0.4)


def test_every_format_agrees_within_one_percent(temporal, tmp_path):
    """The issue's criterion: a known phantom (the temporal bone, three materials, a
    forbidden nerve) written by each format's library loads to the same volumes within 1 %.
    Label maps and CTs keep the voxels at least half bone, so they differ from the
    partial-volume reference by the surface's rounding, not by the loader."""
    bone = temporal
    materials_file = tmp_path / "materials.toml"
    materials_file.write_text(bone_files.materials_toml(bone))
    options = LoadOptions(materials=MaterialMap.from_file(materials_file))
    spacing = LoadOptions(materials=options.materials, spacing_mm=tuple(bone.grid.spacing_mm))
    reference = bone.volumes_mm3()
    loaded = {
        "bone": load_bone(save_bone(bone, tmp_path / "b")),
        "npz": load_bone(bone_files.write_npz(bone, tmp_path / "b.npz"), options),
        "npy": load_bone(bone_files.write_npy(bone, tmp_path / "b.npy"), spacing),
        "nrrd": load_bone(bone_files.write_nrrd_labels(bone, tmp_path / "b.nrrd"), options),
        "nrrd ct": load_bone(bone_files.write_nrrd_ct(bone, tmp_path / "ct.nrrd")),
        "seg.nrrd": load_bone(bone_files.write_seg_nrrd(bone, tmp_path / "b.seg.nrrd"), options),
        "nifti": load_bone(bone_files.write_nifti_labels(bone, tmp_path / "b.nii.gz"), options),
        "nifti ct": load_bone(bone_files.write_nifti_ct(bone, tmp_path / "ct.nii.gz")),
        "png": load_bone(bone_files.write_png_stack(bone, tmp_path / "png"), spacing),
        "dicom": load_bone(bone_files.write_dicom_ct(bone, tmp_path / "dcm")),
    }
    for fmt, result in loaded.items():
        volumes = result.volumes_mm3()
        if fmt == "npy":  # one array, one material: the total
            assert sum(volumes.values()) == pytest.approx(sum(reference.values()), rel=1e-9)
            continue
        for name, volume in reference.items():
            if "ct" in fmt or fmt == "dicom":
                if name == "nerve":  # soft tissue: not bone in a CT
                    continue
            assert volumes[name] == pytest.approx(volume, rel=0.01), (fmt, name, volumes)


# -- geometry conventions -------------------------------------------------------------------
def test_radiological_nifti_is_flipped_to_a_right_handed_grid(tmp_path):
    import nibabel as nib
    values = np.zeros((6, 5, 4), dtype=np.uint8)
    values[0, 1, 2] = 1  # one voxel, at a known place
    affine = np.diag([-0.5, 0.5, 0.5, 1.0])  # LAS storage: det < 0
    affine[:3, 3] = (10.0, -4.0, 2.0)
    image = nib.Nifti1Image(values, affine)
    image.header.set_xyzt_units("mm")
    nib.save(image, tmp_path / "las.nii")
    bone = load_bone(tmp_path / "las.nii", LoadOptions(kind="labels"))
    assert np.linalg.det(bone.grid.direction) == pytest.approx(1.0)
    assert any("flipped" in n for n in bone.notes)
    ras = affine[:3, :3] @ np.array([0, 1, 2]) + affine[:3, 3]
    lps = ras * np.array([-1, -1, 1])
    index = np.argwhere(bone.grid.density > 0)
    assert index.shape == (1, 3)
    np.testing.assert_allclose(bone.grid.voxel_centre_mm(tuple(index[0])), lps, atol=1e-6)


def test_units_are_converted_to_millimetres(tmp_path):
    import nibabel as nib
    import nrrd
    values = np.ones((4, 4, 4), dtype=np.uint8)
    nrrd.write(str(tmp_path / "um.nrrd"), values,
               {"space": "LPS", "space directions": np.eye(3) * 50.0, "space units":
                ["um", "um", "um"], "space origin": [1000.0, 0.0, 0.0]})
    bone = load_bone(tmp_path / "um.nrrd", LoadOptions(kind="labels"))
    np.testing.assert_allclose(bone.grid.spacing_mm, 0.05)
    np.testing.assert_allclose(bone.grid.origin_mm, (1.0, 0.0, 0.0))
    image = nib.Nifti1Image(values, np.diag([0.0002, 0.0002, 0.0002, 1.0]))
    image.header.set_xyzt_units("meter")
    nib.save(image, tmp_path / "m.nii")
    bone = load_bone(tmp_path / "m.nii", LoadOptions(kind="labels"))
    np.testing.assert_allclose(bone.grid.spacing_mm, 0.2, rtol=1e-6)


def test_png_stack_is_ordered_naturally(tmp_path):
    from PIL import Image
    for k in range(12):  # plane00.png … plane011.png: a plain sort puts 10 before 2
        slice_ = np.zeros((3, 4), dtype=np.uint8)
        slice_[0, 0] = 10 * k + 5
        Image.fromarray(slice_, mode="L").save(tmp_path / f"plane0{k}.png")
    bone = load_bone(tmp_path, LoadOptions(kind="density", spacing_mm=(0.1, 0.1, 0.1)))
    assert bone.grid.shape == (3, 4, 12)
    np.testing.assert_array_equal(bone.grid.density[0, 0, :], 10 * np.arange(12) + 5)


# -- CT mapping -------------------------------------------------------------------------------
def test_hu_presets_and_bands(tmp_path):
    hu = np.array([-1000, 0, 147, 148, 400, 661, 662, 1500, 1988, 3000], dtype=np.int16)
    np.savez(tmp_path / "ct.npz", hu=hu.reshape(-1, 1, 1), spacing_mm=[1.0, 1.0, 1.0])
    bone = load_bone(tmp_path / "ct.npz")
    names = [bone.materials.name_of(v) if v else "" for v in bone.grid.labels.ravel()]
    assert names == ["", "", "", "trabecular", "trabecular", "trabecular", "cortical",
                     "cortical", "cortical", "cortical"]
    assert bone.grid.density.ravel().tolist() == [0, 0, 0] + [255] * 7
    no_metal = tmp_path / "no_metal.toml"
    no_metal.write_text("[ct]\nabove_top = false\n")
    bone = load_bone(tmp_path / "ct.npz", LoadOptions(materials=MaterialMap.from_file(no_metal)))
    assert bone.grid.density.ravel()[-1] == 0 and bone.grid.density.ravel()[-2] == 255


def test_partial_volume_ramp_recovers_a_sub_voxel_surface(tmp_path):
    """A bone/air surface 0.3 voxel into a column: linear mixing gives HU = −1000 + f·2300;
    a ramp of the bone–air contrast centred on 148 HU gives back f, a hard threshold cannot."""
    frac = np.array([0.0, 0.0, 0.3, 1.0, 1.0, 1.0])
    hu = (-1000.0 + frac * 2300.0).astype(np.float32).reshape(-1, 1, 1)
    np.savez(tmp_path / "ct.npz", hu=hu, spacing_mm=[1.0, 1.0, 1.0])
    ramp = tmp_path / "ramp.toml"
    ramp.write_text("[ct]\npartial_volume_hu = 2296\n")  # 148 − 1148 … 148 + 1148
    smooth = load_bone(tmp_path / "ct.npz", LoadOptions(materials=MaterialMap.from_file(ramp)))
    assert sum(smooth.volumes_mm3().values()) == pytest.approx(3.3, abs=0.01)
    hard = load_bone(tmp_path / "ct.npz")
    assert sum(hard.volumes_mm3().values()) == pytest.approx(3.0)


def test_materials_file_errors(tmp_path):
    cases = {
        "unknown = 1\n": "unknown keys",
        "[materials.enamel]\nlabels = [1]\n": "give us_n_mm2 and k",
        "[materials.cortical]\nlabels = [0]\n": "empty space",
        "[materials.cortical]\nlabels = [1]\n[materials.trabecular]\nlabels = [1]\n":
            "given to both",
        "[materials.cortical]\nus_n_mm2 = -1\n": "us_n_mm2",
        "[ct]\nbands = [{material = 'x', min_hu = 1, max_hu = 2}]\n": "neither listed",
        "[ct]\nbands = [{material = 'cortical', min_hu = 600, max_hu = 2000},"
        " {material = 'trabecular', min_hu = 100, max_hu = 700}]\n": "overlap",
        "unlisted = 'enamel'\n": "unlisted",
        "not toml [": "materials.toml",
    }
    for text, message in cases.items():
        path = tmp_path / "materials.toml"
        path.write_text(text)
        with pytest.raises(ValueError, match=message):
            MaterialMap.from_file(path)
    json_path = tmp_path / "m.json"
    json_path.write_text(json.dumps({"materials": {"cortical": {"labels": [4]}}}))
    assert MaterialMap.from_file(json_path).rules[0].labels == frozenset({4})


def test_unlisted_labels_follow_the_materials_file(tmp_path):
    values = np.zeros((4, 4, 4), dtype=np.int16)
    values[0] = 7
    values[1] = 1000  # label maps may use any integers
    np.savez(tmp_path / "labels.npz", labels=values, spacing_mm=[0.5])
    own = load_bone(tmp_path / "labels.npz")
    assert sorted(own.volumes_mm3()) == ["label 1000", "label 7"]
    assert all(m.us_n_mm2 == CORTICAL.us_n_mm2 for _, m in own.materials)
    strict = tmp_path / "strict.toml"
    strict.write_text("unlisted = 'error'\n[materials.cortical]\nlabels = [7]\n")
    with pytest.raises(BoneFileError, match="label value 1000"):
        load_bone(tmp_path / "labels.npz", LoadOptions(materials=MaterialMap.from_file(strict)))
    fold = tmp_path / "fold.toml"
    fold.write_text("unlisted = 'cortical'\n[materials.nerve]\nlabels = [7]\n")
    folded = load_bone(tmp_path / "labels.npz", LoadOptions(materials=MaterialMap.from_file(fold)))
    assert folded.volumes_mm3() == pytest.approx({"nerve": 2.0, "cortical": 2.0})


def test_overlapping_segments_let_forbidden_structures_win(tmp_path):
    import nrrd
    bone_layer = np.ones((6, 6, 6), dtype=np.uint8)  # a filled bone segment
    nerve_layer = np.zeros((6, 6, 6), dtype=np.uint8)
    nerve_layer[2:4, 2:4, :] = 1
    header = {"space": "LPS", "space directions": np.vstack([np.full(3, np.nan), np.eye(3)]),
              "kinds": ["list", "domain", "domain", "domain"],
              "Segment0_ID": "a", "Segment0_Name": "Facial nerve", "Segment0_Layer": "1",
              "Segment0_LabelValue": "1", "Segment1_ID": "b", "Segment1_Name": "Bone",
              "Segment1_Layer": "0", "Segment1_LabelValue": "1"}
    nrrd.write(str(tmp_path / "s.seg.nrrd"), np.stack([bone_layer, nerve_layer]), header)
    mapping = tmp_path / "m.toml"
    mapping.write_text("[materials.nerve]\nsegments = ['facial nerve']\n"
                       "[materials.cortical]\nsegments = ['bone']\n")
    bone = load_bone(tmp_path / "s.seg.nrrd", LoadOptions(materials=MaterialMap.from_file(mapping)))
    assert bone.volumes_mm3() == pytest.approx({"nerve": 24.0, "cortical": 216.0 - 24.0})


# -- broken files -----------------------------------------------------------------------------
def _truncate(path: Path, keep: float = 0.5) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    return path


@pytest.mark.parametrize("writer,filename", [
    (bone_files.write_nrrd_labels, "t.nrrd"), (bone_files.write_nifti_labels, "t.nii.gz"),
    (bone_files.write_nifti_ct, "t.nii"), (bone_files.write_npz, "t.npz"),
    (bone_files.write_npy, "t.npy"), (lambda b, p: save_bone(b, p), "t.bone.npz"),
])
def test_truncated_files_fail_cleanly(writer, filename, bone, tmp_path):
    path = _truncate(writer(bone, tmp_path / filename))
    with pytest.raises(BoneFileError) as err:
        load_bone(path, LoadOptions(spacing_mm=(VOXEL_MM,) * 3))
    assert err.value.path == path
    assert str(path) in str(err.value)


def test_truncated_png_slice_names_the_slice(bone, tmp_path):
    folder = bone_files.write_png_stack(bone, tmp_path / "png")
    broken = _truncate(folder / "plane05.png", 0.3)
    with pytest.raises(BoneFileError) as err:
        load_bone(folder, LoadOptions(spacing_mm=(0.4, 0.4, 0.4)))
    assert err.value.path == broken


def test_malformed_and_wrong_files(tmp_path):
    import nrrd
    garbage = tmp_path / "garbage.nrrd"
    garbage.write_bytes(b"NRRD0004\ntype: float\ndimension: banana\n\n")
    with pytest.raises(BoneFileError, match=r"garbage\.nrrd"):
        load_bone(garbage)
    flat = tmp_path / "flat.nrrd"
    nrrd.write(str(flat), np.zeros((4, 4), dtype=np.uint8))
    with pytest.raises(BoneFileError, match="3-D"):
        load_bone(flat)
    notzip = tmp_path / "not.npz"
    notzip.write_bytes(b"hello")
    with pytest.raises(BoneFileError, match=r"not a valid \.npz"):
        load_bone(notzip)
    objects = tmp_path / "obj.npy"
    np.save(objects, np.array([{"a": 1}] * 8, dtype=object).reshape(2, 2, 2))
    with pytest.raises(BoneFileError, match="numbers"):
        load_bone(objects, LoadOptions(spacing_mm=(1, 1, 1)))
    no_spacing = tmp_path / "nospace.npy"
    np.save(no_spacing, np.zeros((3, 3, 3), dtype=np.uint8))
    with pytest.raises(BoneFileError, match="spacing"):
        load_bone(no_spacing)
    nan = tmp_path / "nan.npz"
    np.savez(nan, density=np.full((3, 3, 3), np.nan), spacing_mm=[1.0])
    with pytest.raises(BoneFileError, match="NaN"):
        load_bone(nan)
    with pytest.raises(BoneFileError, match="no such file"):
        load_bone(tmp_path / "missing.nrrd")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(BoneFileError, match="unknown bone format"):
        load_bone(tmp_path / "notes.txt")


def test_absurd_geometry_and_sizes(tmp_path):
    import nrrd
    values = np.ones((4, 4, 4), dtype=np.uint8)
    for directions, message in [(np.eye(3) * 1e-6, "spacing"), (np.eye(3) * 500, "spacing"),
                                (np.array([[1, 0, 0], [0.5, 1, 0], [0, 0, 1.0]]), "sheared"),
                                (np.diag([1.0, 0.0, 1.0]), "zero length")]:
        nrrd.write(str(tmp_path / "g.nrrd"), values,
                   {"space": "LPS", "space directions": directions})
        with pytest.raises(BoneFileError, match=message):
            load_bone(tmp_path / "g.nrrd", LoadOptions(kind="labels"))
    big = tmp_path / "big.npy"
    np.lib.format.open_memmap(big, mode="w+", dtype=np.uint8, shape=(200, 200, 200)).flush()
    with pytest.raises(BoneFileError, match="allowed"):
        load_bone(big, LoadOptions(spacing_mm=(1, 1, 1), max_voxels=1_000_000))
    lying = tmp_path / "lying.npy"  # a header promising far more data than the file holds
    with open(lying, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"descr": "|u1", "fortran_order": False, "shape": (500, 500, 500)})
        f.write(b"\0" * 100)
    with pytest.raises(BoneFileError, match="truncated"):
        load_bone(lying, LoadOptions(spacing_mm=(1, 1, 1)))


def test_detect_format(tmp_path, bone):
    assert detect_format(save_bone(bone, tmp_path / "x")) == "bone"
    assert detect_format(bone_files.write_png_stack(bone, tmp_path / "p")) == "png"
    dicom = bone_files.write_dicom_ct(bone, tmp_path / "d")
    assert detect_format(dicom) == "dicom"
    shutil.copy(next(dicom.iterdir()), tmp_path / "noext")
    assert detect_format(tmp_path / "noext") == "dicom"


# -- files other tools write (not our writers) --------------------------------------------------
def _seg_header(segments: dict[int, dict[str, str]], layered: bool) -> dict:
    spatial = np.eye(3) * 0.5
    header = {"space": "left-posterior-superior",
              "space directions": np.vstack([np.full(3, np.nan), spatial]) if layered
              else spatial}
    if layered:
        header["kinds"] = ["list", "domain", "domain", "domain"]
    for i, fields in segments.items():
        header[f"Segment{i}_ID"] = f"Segment_{i}"
        header.update({f"Segment{i}_{k}": v for k, v in fields.items()})
    return header


def test_legacy_seg_nrrd_puts_each_segment_on_its_own_layer(tmp_path):
    """Older 3D Slicer writes one layer per segment with no Layer or LabelValue fields."""
    import nrrd
    layers = np.zeros((3, 4, 4, 4), dtype=np.uint8)
    layers[0, :2] = 1  # 32 voxels
    layers[1, 2:, :1] = 1  # 8 voxels
    layers[2, 3, 3] = 1  # 4 voxels
    names = {0: {"Name": "Bone"}, 1: {"Name": "Nerve"}, 2: {"Name": "Other"}}
    nrrd.write(str(tmp_path / "old.seg.nrrd"), layers, _seg_header(names, layered=True))
    bone = load_bone(tmp_path / "old.seg.nrrd")
    assert bone.volumes_mm3() == pytest.approx({"Bone": 4.0, "nerve": 1.0, "Other": 0.5})
    # A segment named after a built-in material is that material: the nerve is forbidden.
    assert bone.materials[bone.materials.label_of("nerve")].forbidden
    # A collapsed (3-D) file whose segments lack LabelValue cannot be told apart: an error.
    nrrd.write(str(tmp_path / "flat.seg.nrrd"), layers[0] + 2 * layers[1],
               _seg_header({0: {"Name": "Bone"}, 1: {"Name": "Nerve"}}, layered=False))
    with pytest.raises(BoneFileError, match="both value 1 on layer 0"):
        load_bone(tmp_path / "flat.seg.nrrd")


def test_utf8_segment_names_match_the_materials_file(tmp_path):
    import nrrd
    values = np.zeros((4, 4, 4), dtype=np.uint8)
    values[0] = 1
    values[1] = 2
    name = "Nervus facialis (VII) – rechts é"
    segments = {0: {"Name": "Knochen", "LabelValue": "1", "Layer": "0"},
                1: {"Name": "PLACEHOLDER", "LabelValue": "2", "Layer": "0"}}
    path = tmp_path / "utf8.seg.nrrd"
    nrrd.write(str(path), values, _seg_header(segments, layered=False))
    # pynrrd writes ASCII headers: put the UTF-8 name in, as 3D Slicer writes it.
    head, sep, body = path.read_bytes().partition(b"\n\n")
    path.write_bytes(head.replace(b"PLACEHOLDER", name.encode("utf-8")) + sep + body)
    mapping = tmp_path / "m.toml"
    mapping.write_text(f'unlisted = "error"\n[materials.nerve]\nsegments = ["{name}"]\n'
                       '[materials.cortical]\nsegments = ["knochen"]\n', encoding="utf-8")
    bone = load_bone(path, LoadOptions(materials=MaterialMap.from_file(mapping)))
    assert bone.volumes_mm3() == pytest.approx({"cortical": 2.0, "nerve": 2.0})


@pytest.mark.parametrize("encoding,compress", [("bzip2", "bz2"), ("gzip", "gzip")])
def test_compressed_nrrd_that_inflates_past_its_header_is_refused(encoding, compress, tmp_path):
    import importlib
    header = (f"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: {encoding}\n"
              "space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\n").encode()
    bomb = importlib.import_module(compress).compress(b"\0" * 50_000_000)  # 50 MB in a few kB
    (tmp_path / "bomb.nrrd").write_bytes(header + bomb)
    # gzip's trailer gives the inflated size away before anything is inflated; bzip2 is
    # stopped at the first byte past the header's 8.
    refused = ("inflates to 50,000,000 bytes .* declares 8" if encoding == "gzip"
               else "inflates past the 8 bytes")
    with pytest.raises(BoneFileError, match=refused):
        load_bone(tmp_path / "bomb.nrrd")


def test_gzip_that_hides_its_size_is_stopped_at_the_first_byte_too_many(tmp_path):
    """A trailer forged to agree with the header: the inflating stops one byte past it."""
    import gzip
    header = (b"NRRD0004\ntype: uint8\ndimension: 3\nsizes: 2 2 2\nencoding: gzip\n"
              b"space: LPS\nspace directions: (1,0,0) (0,1,0) (0,0,1)\n\n")
    bomb = bytearray(gzip.compress(b"\0" * 50_000_000))
    bomb[-4:] = (8).to_bytes(4, "little")
    (tmp_path / "forged.nrrd").write_bytes(header + bytes(bomb))
    with pytest.raises(BoneFileError, match="inflates past the 8 bytes"):
        load_bone(tmp_path / "forged.nrrd", LoadOptions(kind="density"))


def test_big_endian_and_half_precision_values(tmp_path):
    import nrrd
    hu = np.full((4, 4, 4), -1000, dtype=">i2")
    hu[:2] = 1300
    nrrd.write(str(tmp_path / "be.nrrd"), hu, {"space": "LPS", "space directions": np.eye(3),
                                               "endian": "big"})
    assert load_bone(tmp_path / "be.nrrd").volumes_mm3() == pytest.approx(
        {"cortical": 32.0, "trabecular": 0.0})
    np.savez(tmp_path / "half.npz", density=np.full((2, 2, 2), 0.5, dtype=np.float16),
             spacing_mm=[1.0])
    assert load_bone(tmp_path / "half.npz").volumes_mm3() == pytest.approx(
        {"cortical": 8 * 128 / 255})


def test_rounded_oblique_directions_are_accepted(tmp_path):
    import nrrd
    rot = _rotation((31.0, -17.0, 52.0))
    rounded = np.round(rot, 5)  # five decimals, as many writers print them
    nrrd.write(str(tmp_path / "oblique.nrrd"), np.ones((3, 3, 3), dtype=np.uint8),
               {"space": "LPS", "space directions": (rounded * 0.25).T})
    bone = load_bone(tmp_path / "oblique.nrrd", LoadOptions(kind="labels"))
    np.testing.assert_allclose(bone.grid.direction, rot, atol=1e-4)
    np.testing.assert_allclose(bone.grid.spacing_mm, 0.25, rtol=1e-4)


def test_nifti_without_orientation_says_so(tmp_path):
    import nibabel as nib
    image = nib.Nifti1Image(np.ones((3, 3, 3), dtype=np.uint8), None)  # codes stay 0
    image.header.set_zooms((0.5, 0.5, 0.5))
    nib.save(image, tmp_path / "noorient.nii")
    bone = load_bone(tmp_path / "noorient.nii", LoadOptions(kind="labels"))
    assert any("no orientation" in note for note in bone.notes)
    np.testing.assert_allclose(bone.grid.spacing_mm, 0.5)


def test_png_slices_of_different_bit_depths_are_refused(tmp_path):
    from PIL import Image
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8), mode="L").save(tmp_path / "s0.png")
    Image.fromarray(np.full((4, 4), 300, dtype=np.uint16)).save(tmp_path / "s1.png")
    with pytest.raises(BoneFileError, match="differs from the first slice"):
        load_bone(tmp_path, LoadOptions(spacing_mm=(1, 1, 1)))


def test_bone_without_a_label_is_an_error(tmp_path):
    density = np.full((2, 2, 2), 255, dtype=np.uint8)
    labels = np.ones((2, 2, 2), dtype=np.uint8)
    labels[0, 0, 0] = 0
    np.savez(tmp_path / "b.npz", density=density, labels=labels, spacing_mm=[1.0])
    with pytest.raises(BoneFileError, match="1 voxels hold bone but have label 0"):
        load_bone(tmp_path / "b.npz")


def test_hu_between_separate_bands_is_not_bone(tmp_path):
    mapping = tmp_path / "gap.toml"
    mapping.write_text("[ct]\nbands = [{material = 'trabecular', min_hu = 148, max_hu = 661},"
                       " {material = 'cortical', min_hu = 700, max_hu = 1988}]\n")
    hu = np.array([600, 661, 661.5, 680, 699, 700], dtype=np.float32).reshape(-1, 1, 1)
    np.savez(tmp_path / "ct.npz", hu=hu, spacing_mm=[1.0])
    bone = load_bone(tmp_path / "ct.npz", LoadOptions(materials=MaterialMap.from_file(mapping)))
    assert bone.grid.density.ravel().tolist() == [255, 255, 0, 0, 0, 255]


def test_auto_detection_does_not_call_a_label_map_a_mask(tmp_path):
    values = np.zeros((4, 4, 4), dtype=np.uint8)
    values[0], values[1], values[2] = 3, 100, 255
    np.save(tmp_path / "v.npy", values)
    bone = load_bone(tmp_path / "v.npy", LoadOptions(spacing_mm=(1, 1, 1)))
    assert bone.kind == "labels"
    mask = np.where(values > 0, np.uint8(255), np.uint8(0))
    np.save(tmp_path / "m.npy", mask)
    assert load_bone(tmp_path / "m.npy", LoadOptions(spacing_mm=(1, 1, 1))).kind == "density"


def test_a_detached_data_file_must_lie_beside_its_header(tmp_path):
    """An .nhdr's voxels may sit in a file beside it; one naming a path elsewhere (absolute,
    or up through ..) is refused: an uploaded header must not read the server's files."""
    folder = tmp_path / "bone"
    folder.mkdir()
    voxels = np.zeros((4, 4, 4), dtype=np.uint8)
    voxels[1:3, 1:3, 1:3] = 1
    (folder / "voxels.raw").write_bytes(voxels.tobytes())
    (tmp_path / "outside.raw").write_bytes(voxels.tobytes())

    def header(data_file: str) -> Path:
        path = folder / "bone.nhdr"
        path.write_text("NRRD0004\ntype: uint8\ndimension: 3\nsizes: 4 4 4\n"
                        f"spacings: 0.5 0.5 0.5\nencoding: raw\ndata file: {data_file}\n\n")
        return path

    bone = load_bone(header("voxels.raw"), LoadOptions(kind="labels"))
    assert bone.grid.shape == (4, 4, 4) and (bone.grid.labels == 1).sum() == 8
    for elsewhere in ("../outside.raw", str(tmp_path / "outside.raw"), "/etc/hostname"):
        with pytest.raises(BoneFileError, match="lies outside the header's folder"):
            load_bone(header(elsewhere), LoadOptions(kind="labels"))
