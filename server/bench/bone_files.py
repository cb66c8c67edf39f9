"""Write a bone in every format the loaders read, with the formats' own libraries.

For the round-trip tests and ``burrforce bench load``: a known bone goes out through pynrrd,
nibabel, pydicom, Pillow and NumPy, and must come back with the same volumes. A label map
keeps a voxel where at least half of it is bone; a CT gives each material a fixed HU and
empty voxels air, so thresholds recover the same voxels.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import numpy as np

from ..bone.bone import Bone

#: Hounsfield units written for each material (inside its preset band); air outside.
MATERIAL_HU = {"cortical": 1300, "trabecular": 400}
AIR_HU = -1000
#: RAS ← LPS: NIfTI stores RAS.
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])


def label_map(bone: Bone) -> np.ndarray:
    """(nx, ny, nz) uint8: the bone's label where a voxel is at least half bone, else 0."""
    grid = bone.grid
    return np.where(grid.remaining_density() >= 128, grid.labels, np.uint8(0))


def hu_volume(bone: Bone) -> np.ndarray:
    """(nx, ny, nz) int16 HU: MATERIAL_HU per material in label_map, air elsewhere (other
    materials — a nerve — are soft tissue at 40 HU)."""
    labels = label_map(bone)
    hu = np.full(labels.shape, AIR_HU, dtype=np.int16)
    for label, material in bone.materials:
        hu[labels == label] = MATERIAL_HU.get(material.name, 40)
    return hu


def materials_toml(bone: Bone) -> str:
    """A materials file mapping the bone's labels, names (segments) and colours back to its
    materials."""
    out = []
    for label, material in bone.materials:
        out += [f'[materials."{material.name}"]', f"us_n_mm2 = {material.us_n_mm2!r}",
                f"k = {material.k!r}", f"forbidden = {str(material.forbidden).lower()}",
                f"labels = [{label}]", f'segments = ["{material.name}"]',
                f'colors = ["{label_colour_hex(label)}"]', ""]
    return "\n".join(out)


def label_colour(label: int) -> tuple[int, int, int]:
    """A distinct colour per label (for RGBA PNG stacks)."""
    return ((label * 97) % 256, (label * 57 + 80) % 256, (label * 151 + 30) % 256)


def label_colour_hex(label: int) -> str:
    return "#{:02x}{:02x}{:02x}".format(*label_colour(label))


def write_npy(bone: Bone, path: Path) -> Path:
    np.save(path, bone.grid.remaining_density())
    return path


def write_npz(bone: Bone, path: Path) -> Path:
    grid = bone.grid
    np.savez_compressed(path, density=grid.remaining_density(), labels=grid.labels,
                        spacing_mm=grid.spacing_mm, origin_mm=grid.origin_mm,
                        direction=grid.direction)
    return path


def write_nrrd_labels(bone: Bone, path: Path) -> Path:
    import nrrd
    grid = bone.grid
    nrrd.write(str(path), label_map(bone), {
        "space": "left-posterior-superior",
        "space directions": grid.direction.T * grid.spacing_mm[:, None],
        "space origin": grid.origin_mm, "space units": ["mm", "mm", "mm"]})
    return path


def write_nrrd_ct(bone: Bone, path: Path) -> Path:
    """A CT in RAS (as older 3D Slicer writes), to exercise the frame conversion."""
    import nrrd
    grid = bone.grid
    axes_ras = _LPS_TO_RAS @ (grid.direction * grid.spacing_mm)
    nrrd.write(str(path), hu_volume(bone), {
        "space": "right-anterior-superior", "space directions": axes_ras.T,
        "space origin": _LPS_TO_RAS @ grid.origin_mm})
    return path


def write_seg_nrrd(bone: Bone, path: Path, layered: bool = False) -> Path:
    """A 3D Slicer segmentation: one segment per material, named after it; ``layered`` puts
    each segment on its own layer (4-D), as Slicer does when segments overlap."""
    import nrrd
    grid = bone.grid
    labels = label_map(bone)
    header = {"space": "left-posterior-superior",
              "space origin": grid.origin_mm}
    spatial = grid.direction.T * grid.spacing_mm[:, None]
    segments = list(bone.materials)
    if layered:
        data = np.stack([(labels == label).astype(np.uint8) for label, _ in segments])
        header["space directions"] = np.vstack([np.full(3, np.nan), spatial])
        header["kinds"] = ["list", "domain", "domain", "domain"]
    else:
        data = labels
        header["space directions"] = spatial
    for i, (label, material) in enumerate(segments):
        colour = " ".join(f"{c / 255:.6f}" for c in label_colour(label))
        header.update({f"Segment{i}_ID": f"Segment_{i}", f"Segment{i}_Name": material.name,
                       f"Segment{i}_Color": colour,
                       f"Segment{i}_LabelValue": "1" if layered else str(label),
                       f"Segment{i}_Layer": str(i if layered else 0)})
    nrrd.write(str(path), data, header)
    return path


def _nifti_affine(bone: Bone) -> np.ndarray:
    grid = bone.grid
    affine = np.eye(4)
    affine[:3, :3] = _LPS_TO_RAS @ (grid.direction * grid.spacing_mm)
    affine[:3, 3] = _LPS_TO_RAS @ grid.origin_mm
    return affine


def write_nifti_labels(bone: Bone, path: Path) -> Path:
    import nibabel as nib
    image = nib.Nifti1Image(label_map(bone), _nifti_affine(bone))
    image.header.set_xyzt_units("mm")
    image.header.set_intent("label")
    nib.save(image, str(path))
    return path


def write_nifti_ct(bone: Bone, path: Path) -> Path:
    import nibabel as nib
    image = nib.Nifti1Image(hu_volume(bone), _nifti_affine(bone))
    image.header.set_xyzt_units("mm")
    nib.save(image, str(path))
    return path


def write_dicom_ct(bone: Bone, folder: Path) -> Path:
    """A CT series, one file per k-slice, stored as unsigned pixels with intercept −1024; file
    names are shuffled so only the geometry orders them."""
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import CTImageStorage, ExplicitVRLittleEndian, generate_uid

    folder.mkdir(parents=True, exist_ok=True)
    grid = bone.grid
    hu = hu_volume(bone)
    nx, ny, nz = hu.shape
    series, study, frame = generate_uid(), generate_uid(), generate_uid()
    row_dir, col_dir = grid.direction[:, 0], grid.direction[:, 1]
    names = np.random.default_rng(0).permutation(nz)
    for k in range(nz):
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = CTImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        name = folder / f"IM{names[k]:05d}"
        ds = FileDataset(str(name), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.SOPClassUID = CTImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.SeriesInstanceUID, ds.StudyInstanceUID, ds.FrameOfReferenceUID = series, study, frame
        ds.SeriesDescription = bone.name or "burrforce bone"
        ds.ContentDate = dt.date.today().strftime("%Y%m%d")
        ds.InstanceNumber = int(names[k]) + 1
        position = grid.to_world_point(np.array([0.0, 0.0, k * grid.spacing_mm[2]]))
        ds.ImagePositionPatient = [f"{v:.6f}" for v in position]
        ds.ImageOrientationPatient = [f"{v:.8f}" for v in (*row_dir, *col_dir)]
        ds.PixelSpacing = [f"{grid.spacing_mm[1]:.6f}", f"{grid.spacing_mm[0]:.6f}"]
        ds.SliceThickness = f"{grid.spacing_mm[2]:.6f}"
        ds.Rows, ds.Columns = ny, nx
        ds.SamplesPerPixel = 1
        ds.PhotometricInterpretation = "MONOCHROME2"
        ds.BitsAllocated = ds.BitsStored = 16
        ds.HighBit = 15
        ds.PixelRepresentation = 0
        ds.RescaleSlope, ds.RescaleIntercept = 1, -1024
        ds.PixelData = (hu[:, :, k].T.astype(np.int32) + 1024).astype("<u2").tobytes()
        ds.save_as(name, enforce_file_format=True)
    return folder


def write_png_stack(bone: Bone, folder: Path) -> Path:
    """RGBA slices as volumetric_drilling writes them: pixel (row, col) of file ``plane0{k}``
    is voxel (row, col, k); each label its colour, alpha 255; empty space transparent. The
    names are not zero-padded, so only a natural sort orders them."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    labels = label_map(bone)
    lut = np.zeros((256, 4), dtype=np.uint8)
    for label, _ in bone.materials:
        lut[label] = (*label_colour(label), 255)
    for k in range(labels.shape[2]):
        Image.fromarray(lut[labels[:, :, k]], mode="RGBA").save(folder / f"plane0{k}.png")
    return folder


def write_png_gray(bone: Bone, folder: Path) -> Path:
    """8-bit grayscale slices of the density (0–255)."""
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    density = bone.grid.remaining_density()
    for k in range(density.shape[2]):
        Image.fromarray(np.ascontiguousarray(density[:, :, k]), mode="L").save(
            folder / f"slice{k}.png")
    return folder


def _save_compact(bone: Bone, path: Path) -> Path:
    from ..bone.loaders import save_bone
    return save_bone(bone, path)


#: Every way this module writes a bone: format name → (writer, file or folder name).
FORMAT_WRITERS = {
    "bone": (_save_compact, "bone.bone.npz"),
    "npz": (write_npz, "bone.npz"),
    "npy": (write_npy, "bone.npy"),
    "nrrd": (write_nrrd_labels, "labels.nrrd"),
    "nrrd-ct": (write_nrrd_ct, "ct.nrrd"),
    "seg.nrrd": (write_seg_nrrd, "bone.seg.nrrd"),
    "nifti": (write_nifti_labels, "labels.nii.gz"),
    "nifti-raw": (write_nifti_labels, "labels.nii"),
    "nifti-ct": (write_nifti_ct, "ct.nii.gz"),
    "dicom": (write_dicom_ct, "dicom"),
    "png": (write_png_stack, "png"),
    "png-gray": (write_png_gray, "gray"),
}


def write(bone: Bone, fmt: str, folder: Path) -> Path:
    """Write ``bone`` in format ``fmt`` (a FORMAT_WRITERS key) into ``folder``; its path."""
    writer, name = FORMAT_WRITERS[fmt]
    return writer(bone, folder / name)
