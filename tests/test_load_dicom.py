"""DICOM series loading: pydicom's sample CT series, series written here with a known HU volume
and geometry, and broken folders (truncated, missing, mismatched, tilted, mixed slices)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pydicom
import pytest
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.uid import (
    CTImageStorage,
    ExplicitVRLittleEndian,
    JPEG2000Lossless,
    MRImageStorage,
    generate_uid,
)
from pydicom.valuerep import format_number_as_ds

from burrforce.server.bone.hounsfield import CORTICAL_HU, TRABECULAR_HU
from burrforce.server.bone.loaders import BoneFileError, LoadOptions, load_bone
from burrforce.server.bone.loaders.dicom_series import read_dicom_series

TEST_FILES = Path(pydicom.__file__).parent / "data" / "test_files"
CT5N = "dicomdirtests/98892001/CT5N"  # 5 CT slices, file names running opposite to z
CT2 = "dicomdirtests/77654033/CT2"  # 4 CT slices: −99.48, then 103.02, 104.27, 105.52 mm
CT2N = "dicomdirtests/98892001/CT2N"  # 2 scouts in different orientations

#: Geometry of the written series: an oblique grid with unequal spacing, mm.
SPACING_MM = (0.4, 0.55, 1.25)
ORIGIN_MM = (-12.5, 30.25, 101.125)
SHAPE = (12, 10, 8)  # (Columns, Rows, slices)


def sample(relative: str) -> Path:
    """A file or folder of pydicom's test data; skip the test when it is not installed."""
    path = TEST_FILES / relative
    if not path.exists():
        pytest.skip(f"pydicom test data {relative} not installed")
    return path


def copy_files(source: Path, folder: Path) -> Path:
    """Copy the files of ``source`` (a folder, or one file) into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    for file in [source] if source.is_file() else sorted(source.iterdir()):
        if file.is_file():
            shutil.copy(file, folder / file.name)
    return folder


def oblique_rotation() -> np.ndarray:
    """A rotation aligned with no axis: 0.5 rad about (1, 2, 3) (Rodrigues' formula)."""
    axis = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]],
                  [-axis[1], axis[0], 0.0]])
    angle = 0.5
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def ds_values(values) -> list[str]:
    """Numbers as DICOM decimal strings (at most 16 characters each)."""
    return [format_number_as_ds(float(v)) for v in values]


def write_slice(
    path: Path, pixels: np.ndarray, position_mm, *, direction: np.ndarray,
    spacing_mm=SPACING_MM, series_uid: str, slope: float = 1.0, intercept: float = -1024.0,
    modality: str = "CT", instance: int = 1, frames: int = 1,
) -> Path:
    """One single-frame slice; ``pixels`` is (Columns, Rows): pixels[i, j] is row j, column i.

    With ``frames`` > 1 the same pixels repeat as the frames of one multi-frame file.
    """
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CTImageStorage if modality == "CT" else MRImageStorage
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID = "1.2.826.0.1.3680043.8.498.1"
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = "1.2.826.0.1.3680043.8.498.2"
    ds.Modality = modality
    ds.SeriesDescription = "written by test_load_dicom"
    ds.InstanceNumber = instance
    ds.Columns, ds.Rows = pixels.shape
    ds.PixelSpacing = ds_values((spacing_mm[1], spacing_mm[0]))  # [between rows, columns]
    ds.ImageOrientationPatient = ds_values(np.concatenate((direction[:, 0], direction[:, 1])))
    ds.ImagePositionPatient = ds_values(position_mm)
    ds.SliceThickness = format_number_as_ds(float(spacing_mm[2]))
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 1 if pixels.dtype == np.int16 else 0
    ds.RescaleSlope = format_number_as_ds(float(slope))
    ds.RescaleIntercept = format_number_as_ds(float(intercept))
    stored = np.ascontiguousarray(pixels.T).astype(pixels.dtype.newbyteorder("<"))
    if frames > 1:
        ds.NumberOfFrames = frames
        stored = np.concatenate([stored] * frames)
    ds.PixelData = stored.tobytes()
    ds.save_as(path, enforce_file_format=True)
    return path


def write_series(
    folder: Path, stored: np.ndarray, *, direction: np.ndarray | None = None,
    spacing_mm=SPACING_MM, origin_mm=ORIGIN_MM, series_uid: str | None = None,
    seed: int = 0, **slice_args,
) -> list[Path]:
    """A series from ``stored`` (Columns, Rows, slices) pixel values, slice k at origin + k ·
    step along the normal. File names and InstanceNumbers are shuffled so that neither gives
    the order. Returns the files in slice order."""
    folder.mkdir(parents=True, exist_ok=True)
    direction = np.eye(3) if direction is None else direction
    series_uid = series_uid or generate_uid()
    n = stored.shape[2]
    names = np.random.default_rng(seed).permutation(n)
    files = []
    for k in range(n):
        position = np.asarray(origin_mm) + k * spacing_mm[2] * direction[:, 2]
        files.append(write_slice(folder / f"IM{names[k]:04d}.dcm", stored[:, :, k], position,
                                 direction=direction, spacing_mm=spacing_mm,
                                 series_uid=series_uid, instance=int(names[n - 1 - k]) + 1,
                                 **slice_args))
    return files


def ct_pixels(shape=SHAPE, seed: int = 1) -> np.ndarray:
    """Stored values 0..3999 (HU −1024..2975 with intercept −1024): air to dense bone, with
    each band's edges present."""
    rng = np.random.default_rng(seed)
    stored = rng.integers(0, 4000, size=shape).astype(np.uint16)
    edges = np.array([TRABECULAR_HU[0] - 1, TRABECULAR_HU[0], TRABECULAR_HU[1],
                      CORTICAL_HU[0], CORTICAL_HU[1], CORTICAL_HU[1] + 1]) + 1024
    stored.reshape(-1)[:edges.size] = edges
    return stored


# ---------------------------------------------------------------------------------------------
# pydicom's sample series


def test_ct5n_is_ordered_by_geometry_not_by_file_name(tmp_path):
    folder = copy_files(sample(CT5N), tmp_path / "CT5N")
    files = sorted(folder.iterdir())
    z_by_name = [float(pydicom.dcmread(f).ImagePositionPatient[2]) for f in files]
    assert z_by_name == sorted(z_by_name, reverse=True)  # the names run opposite to z

    calls = []
    raw = read_dicom_series(folder, LoadOptions(), lambda *args: calls.append(args))
    assert calls == []  # headers only: the pixels are decoded as the converter reads them
    hu = raw.data.array()
    assert hu.shape == (16, 16, 5) and hu.dtype == np.int16
    assert raw.kind == "ct" and raw.format == "dicom"
    assert raw.origin_mm == pytest.approx([-72.199997, -143.0, -1.2375])
    assert raw.spacing_mm == pytest.approx([0.488281, 0.488281, 2.5])
    assert np.allclose(raw.direction, np.eye(3))
    load_bone(folder, progress=lambda *args: calls.append(args))
    assert calls[-1] == ("converting", 5, 5)
    for file in files:
        ds = pydicom.dcmread(file)
        k = round((float(ds.ImagePositionPatient[2]) - raw.origin_mm[2]) / 2.5)
        expected = ds.pixel_array.T.astype(np.int64) - 1024
        np.testing.assert_array_equal(hu[:, :, k], expected)

    bone = load_bone(folder)
    assert bone.kind == "ct" and bone.format == "dicom"
    assert bone.grid.shape == (16, 16, 5)
    assert bone.grid.spacing_mm == pytest.approx([0.488281, 0.488281, 2.5])
    assert bone.grid.origin_mm == pytest.approx([-72.199997, -143.0, -1.2375])


def test_ct2_with_a_gap_says_slices_are_missing(tmp_path):
    folder = copy_files(sample(CT2), tmp_path / "CT2")
    with pytest.raises(BoneFileError, match="slices are missing") as err:
        load_bone(folder)
    assert "202.5 mm" in str(err.value) and "1.25 mm" in str(err.value)


def test_scouts_in_different_orientations_are_refused(tmp_path):
    folder = copy_files(sample(CT2N), tmp_path / "CT2N")
    with pytest.raises(BoneFileError, match="ImageOrientationPatient"):
        load_bone(folder)


def test_two_series_in_one_folder_must_be_chosen(tmp_path):
    folder = copy_files(sample(CT5N), tmp_path / "mixed")
    copy_files(sample(CT2), folder)
    ct5n_uid = pydicom.dcmread(sample(CT5N) / "2062").SeriesInstanceUID
    ct2_uid = pydicom.dcmread(sample(CT2) / "17106").SeriesInstanceUID

    with pytest.raises(BoneFileError) as err:
        load_bone(folder)
    message = str(err.value)
    assert ct5n_uid in message and ct2_uid in message
    assert "5 slices" in message and "4 slices" in message and "series_uid" in message
    assert "SmartScore" in message and "CT" in message

    bone = load_bone(folder, LoadOptions(series_uid=ct5n_uid))
    assert bone.grid.shape == (16, 16, 5)
    assert any("other series" in note for note in bone.notes)

    with pytest.raises(BoneFileError, match=r"no series 1\.2\.3\.4") as err:
        load_bone(folder, LoadOptions(series_uid="1.2.3.4"))
    assert ct5n_uid in str(err.value) and ct2_uid in str(err.value)

    # One file of a series: that series, read from the files beside it.
    assert load_bone(folder / "2392").grid.shape == (16, 16, 5)
    with pytest.raises(BoneFileError, match="belongs to series"):
        load_bone(folder / "2392", LoadOptions(series_uid=ct2_uid))


def test_a_single_slice_takes_its_step_from_the_header(tmp_path):
    folder = copy_files(sample("CT_small.dcm"), tmp_path / "small")
    for path in (folder, folder / "CT_small.dcm"):
        bone = load_bone(path)
        assert bone.grid.shape == (128, 128, 1)
        assert bone.grid.spacing_mm == pytest.approx([0.661468, 0.661468, 5.0])
        assert bone.grid.origin_mm == pytest.approx([-158.135803, -179.035797, -75.699997])
        assert any("single slice" in note for note in bone.notes)


# ---------------------------------------------------------------------------------------------
# Series written here: exact round trips


def test_oblique_series_round_trips_hu_and_geometry(tmp_path):
    rotation = oblique_rotation()
    stored = ct_pixels()
    write_series(tmp_path / "oblique", stored, direction=rotation)
    hu = stored.astype(np.int64) - 1024

    raw = read_dicom_series(tmp_path / "oblique", LoadOptions(), None)
    assert raw.data.array().dtype == np.int16
    np.testing.assert_array_equal(raw.data.array(), hu)
    np.testing.assert_allclose(raw.spacing_mm, SPACING_MM, atol=1e-9)
    np.testing.assert_allclose(raw.origin_mm, ORIGIN_MM, atol=1e-9)
    np.testing.assert_allclose(raw.direction, rotation, atol=1e-9)
    assert raw.kind == "ct" and raw.notes == []

    bone = load_bone(tmp_path / "oblique")
    grid = bone.grid
    assert bone.kind == "ct" and grid.shape == SHAPE
    np.testing.assert_allclose(grid.direction, rotation, atol=1e-9)
    np.testing.assert_allclose(grid.origin_mm, ORIGIN_MM, atol=1e-9)
    np.testing.assert_allclose(grid.spacing_mm, SPACING_MM, atol=1e-9)
    np.testing.assert_array_equal(grid.density > 0, hu >= TRABECULAR_HU[0])
    names = np.array([bone.materials.name_of(int(label)) if label else ""
                      for label in range(256)])
    expected = np.where(hu >= CORTICAL_HU[0], "cortical",
                        np.where(hu >= TRABECULAR_HU[0], "trabecular", ""))
    np.testing.assert_array_equal(names[grid.labels], expected)


def test_signed_pixels_without_intercept_stay_int16(tmp_path):
    stored = (ct_pixels().astype(np.int32) - 1024).astype(np.int16)
    write_series(tmp_path / "signed", stored, intercept=0.0)
    raw = read_dicom_series(tmp_path / "signed", LoadOptions(), None)
    assert raw.data.array().dtype == np.int16
    np.testing.assert_array_equal(raw.data.array(), stored)


def test_non_integer_slope_gives_float32(tmp_path):
    stored = ct_pixels()
    write_series(tmp_path / "float", stored, slope=0.5, intercept=-1000.25)
    raw = read_dicom_series(tmp_path / "float", LoadOptions(), None)
    assert raw.data.array().dtype == np.float32
    np.testing.assert_array_equal(raw.data.array(), stored * 0.5 - 1000.25)  # exact: quarters


def test_values_beyond_int16_widen_to_float32(tmp_path):
    stored = ct_pixels()
    stored[3, 4, 5] = 40000  # HU 38976 in the sixth slice: the first five were int16
    write_series(tmp_path / "wide", stored)
    raw = read_dicom_series(tmp_path / "wide", LoadOptions(), None)
    assert raw.data.array().dtype == np.float32
    np.testing.assert_array_equal(raw.data.array(), stored.astype(np.int64) - 1024)


def test_series_with_descending_positions_is_flipped_into_order(tmp_path):
    # Slices written with the normal pointing down (feet first): the array still runs up the
    # normal, the origin is the lowest slice and the grid stays right-handed.
    flip = np.diag([1.0, -1.0, -1.0])  # rows run posterior → anterior, normal −z
    stored = ct_pixels((6, 5, 4))
    write_series(tmp_path / "down", stored, direction=flip, spacing_mm=(0.5, 0.5, 1.0))
    raw = read_dicom_series(tmp_path / "down", LoadOptions(), None)
    np.testing.assert_allclose(raw.direction, flip, atol=1e-12)
    assert np.linalg.det(raw.direction) == pytest.approx(1.0)
    np.testing.assert_array_equal(raw.data.array(), stored.astype(np.int64) - 1024)


# ---------------------------------------------------------------------------------------------
# Broken input


def test_truncated_slice_is_named(tmp_path):
    files = write_series(tmp_path / "cut", ct_pixels((32, 32, 6)))
    victim = files[3]
    content = victim.read_bytes()
    victim.write_bytes(content[:len(content) // 2])
    with pytest.raises(BoneFileError) as err:
        load_bone(tmp_path / "cut")
    assert err.value.path == victim


def test_slice_cut_before_its_pixel_data_is_named(tmp_path):
    files = write_series(tmp_path / "cut", ct_pixels((8, 8, 5)))
    victim = files[0]  # an end slice: the step check alone would not notice it gone
    with open(victim, "rb") as f:
        pydicom.dcmread(f, stop_before_pixels=True)
        header_bytes = f.tell()
    victim.write_bytes(victim.read_bytes()[:header_bytes])
    with pytest.raises(BoneFileError, match="no pixel data") as err:
        load_bone(tmp_path / "cut")
    assert err.value.path == victim


def test_missing_middle_slice(tmp_path):
    files = write_series(tmp_path / "gap", ct_pixels((6, 5, 6)))
    files[3].unlink()
    with pytest.raises(BoneFileError, match=r"slices are missing.*2\.5 mm.*step is 1\.25 mm"):
        load_bone(tmp_path / "gap")


def test_two_slices_at_one_position(tmp_path):
    files = write_series(tmp_path / "twice", ct_pixels((6, 5, 4)))
    shutil.copy(files[2], tmp_path / "twice" / "copy.dcm")
    with pytest.raises(BoneFileError, match="same position"):
        load_bone(tmp_path / "twice")


def test_mismatched_rows_name_the_odd_slice(tmp_path):
    series_uid = generate_uid()
    files = write_series(tmp_path / "rows", ct_pixels((6, 5, 5)), series_uid=series_uid)
    position = [float(v) for v in pydicom.dcmread(files[2]).ImagePositionPatient]
    write_slice(files[2], ct_pixels((6, 7, 1))[:, :, 0], position, direction=np.eye(3),
                series_uid=series_uid)  # 7 rows where the others have 5
    with pytest.raises(BoneFileError, match="Rows 7 differs from 5") as err:
        load_bone(tmp_path / "rows")
    assert err.value.path == files[2]


def test_tilted_gantry_is_refused(tmp_path):
    # Slice origins step along z while the slices lie in the x-y plane tilted by 5° about x:
    # the normal is not the stacking direction.
    tilt = np.radians(5.0)
    direction = np.array([[1.0, 0.0, 0.0],
                          [0.0, np.cos(tilt), np.sin(tilt)],
                          [0.0, -np.sin(tilt), np.cos(tilt)]])
    folder = tmp_path / "tilt"
    folder.mkdir()
    series_uid = generate_uid()
    pixels = ct_pixels((6, 5, 4))
    for k in range(4):
        write_slice(folder / f"{k}.dcm", pixels[:, :, k], (0.0, 0.0, 1.25 * k),
                    direction=direction, series_uid=series_uid)
    with pytest.raises(BoneFileError, match="resample"):
        load_bone(folder)


def test_junk_files_beside_the_slices_are_ignored(tmp_path):
    folder = tmp_path / "junk"
    stored = ct_pixels((6, 5, 4))
    write_series(folder, stored)
    (folder / "notes.txt").write_text("scanned on a Tuesday\n")
    (folder / "README").write_text("not DICOM either\n")
    (folder / "junk.dcm").write_bytes(np.random.default_rng(3).bytes(700))
    (folder / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")
    (folder / "DICOMDIR").write_bytes(b"not read")
    (folder / "sub").mkdir()
    raw = read_dicom_series(folder, LoadOptions(), None)
    np.testing.assert_array_equal(raw.data.array(), stored.astype(np.int64) - 1024)
    assert any("skipped 4 file(s)" in note for note in raw.notes)
    assert load_bone(folder).grid.shape == (6, 5, 4)


def test_folder_without_images(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(BoneFileError, match="no DICOM image files"):
        read_dicom_series(empty, LoadOptions(), None)
    with pytest.raises(BoneFileError):
        load_bone(empty)
    (empty / "junk.dcm").write_text("hello\n")
    with pytest.raises(BoneFileError, match=r"no DICOM image files.*not DICOM"):
        load_bone(empty)


def test_mr_needs_an_explicit_kind(tmp_path):
    stored = ct_pixels((6, 5, 3))
    write_series(tmp_path / "mr", stored, modality="MR", intercept=0.0)
    with pytest.raises(BoneFileError, match=r"MR, not CT.*kind"):
        load_bone(tmp_path / "mr")
    raw = read_dicom_series(tmp_path / "mr", LoadOptions(kind="ct"), None)
    np.testing.assert_array_equal(raw.data.array(), stored)
    assert load_bone(tmp_path / "mr", LoadOptions(kind="ct")).kind == "ct"


def test_too_many_voxels_is_refused_before_pixels_are_read(tmp_path):
    files = write_series(tmp_path / "big", ct_pixels())
    for file in files:  # every slice's pixels are damaged: reading any would fail differently
        file.write_bytes(file.read_bytes()[:-10])
    with pytest.raises(BoneFileError, match="more than the 100 allowed"):
        load_bone(tmp_path / "big", LoadOptions(max_voxels=100))
    with pytest.raises(BoneFileError, match="cannot decode"):
        load_bone(tmp_path / "big")


def test_multi_frame_files_are_refused(tmp_path):
    folder = tmp_path / "multi"
    folder.mkdir()
    write_slice(folder / "all.dcm", ct_pixels((6, 5, 1))[:, :, 0], ORIGIN_MM,
                direction=np.eye(3), series_uid=generate_uid(), frames=3)
    with pytest.raises(BoneFileError, match=r"multi-frame.*not supported"):
        load_bone(folder)


def test_undecodable_pixel_data_is_named(tmp_path):
    files = write_series(tmp_path / "j2k", ct_pixels((6, 5, 3)))
    ds = pydicom.dcmread(files[1])
    ds.file_meta.TransferSyntaxUID = JPEG2000Lossless
    ds.PixelData = encapsulate([b"\xff\x4f\xff\x51 not a codestream"])
    ds["PixelData"].VR = "OB"
    ds.save_as(files[1], enforce_file_format=True)
    with pytest.raises(BoneFileError, match="cannot decode its pixel data") as err:
        load_bone(tmp_path / "j2k")
    assert err.value.path == files[1]


def test_single_slice_without_thickness(tmp_path):
    files = write_series(tmp_path / "one", ct_pixels((6, 5, 1)))
    ds = pydicom.dcmread(files[0])
    del ds.SliceThickness
    ds.save_as(files[0], enforce_file_format=True)
    with pytest.raises(BoneFileError, match="thickness is unknown"):
        load_bone(tmp_path / "one")
