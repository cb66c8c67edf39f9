"""NumPy files: ``.npy`` (one array, geometry from the caller) and ``.npz`` (arrays with their
geometry, or burrforce's own ``.bone.npz``)."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from ..bone import Bone
from .compact import is_compact, read_compact
from .convert import LoadOptions, check_size
from .errors import BoneFileError
from .geometry import from_axes
from .npy_member import MAX_META_ELEMENTS, member_source, npy_source, read_member
from .volume import RawVolume

#: .npz keys for the voxels, and what each means.
VOLUME_KEYS = {"hu": "ct", "ct": "ct", "density": "density", "labels": "labels",
               "volume": "auto", "arr_0": "auto"}
GEOMETRY_KEYS = ("spacing_mm", "origin_mm", "direction")


def read_npy(path: Path, options: LoadOptions) -> RawVolume:
    """A ``.npy`` volume; its spacing must come from ``options.spacing_mm``."""
    if options.spacing_mm is None:
        raise BoneFileError(path, "a .npy file has no voxel size: give spacing_mm "
                                  "(--spacing-mm), or use .npz with a spacing_mm array")
    data = npy_source(path, options.max_voxels)
    check_size(path, data.shape, options)
    # The converter applies options.spacing_mm and options.origin_mm (and notes them).
    return RawVolume(path, "npy", data, np.asarray(options.spacing_mm, dtype=np.float64),
                     np.zeros(3), np.eye(3),
                     notes=["no geometry in a .npy: identity orientation"])


def read_npz(path: Path, options: LoadOptions) -> RawVolume | Bone:
    """A ``.npz`` volume with its geometry arrays, or a burrforce ``.bone.npz``."""
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, ValueError) as exc:
        raise BoneFileError(path, f"not a valid .npz (zip) file: {exc}") from None
    with archive:
        if is_compact(archive):
            return read_compact(path, archive, options.max_voxels, options.memory_budget_bytes)
        keys = {n[:-4] for n in archive.namelist() if n.endswith(".npy")}
        volume_keys = [k for k in VOLUME_KEYS if k in keys]
        if not volume_keys:
            raise BoneFileError(path, f"no volume in it: expected one of "
                                      f"{', '.join(VOLUME_KEYS)}; found {sorted(keys)}")
        main = "density" if "density" in volume_keys else volume_keys[0]
        data = member_source(path, archive, main, options.max_voxels)
        check_size(path, data.shape, options)
        labels = None
        kind = VOLUME_KEYS[main]
        if main == "density" and "labels" in keys:
            labels = member_source(path, archive, "labels", options.max_voxels)
        meta = {k: read_member(path, archive, k, MAX_META_ELEMENTS)
                for k in GEOMETRY_KEYS if k in keys}
    if "spacing_mm" in meta:
        spacing = np.asarray(meta["spacing_mm"], dtype=np.float64).reshape(-1)
        if spacing.shape == (1,):
            spacing = np.repeat(spacing, 3)
        if spacing.shape != (3,):
            raise BoneFileError(path, f"spacing_mm must be 1 or 3 numbers, got "
                                      f"{spacing.tolist()}")
    elif options.spacing_mm is not None:
        spacing = np.asarray(options.spacing_mm, dtype=np.float64)
    else:
        raise BoneFileError(path, "no spacing_mm array in it and none given (--spacing-mm)")
    origin = np.asarray(meta.get("origin_mm", (0.0, 0.0, 0.0)), dtype=np.float64).reshape(-1)
    if origin.shape != (3,):
        raise BoneFileError(path, f"origin_mm must be 3 numbers, got {origin.tolist()}")
    direction = np.asarray(meta.get("direction", np.eye(3)), dtype=np.float64)
    if direction.shape != (3, 3):
        raise BoneFileError(path, f"direction must be 3×3, got shape {direction.shape}")
    # Unit columns are checked (and a negative spacing folded into its axis) by from_axes.
    spacing, unit_dirs = from_axes(path, direction * spacing)
    return RawVolume(path, "npz", data, spacing, origin, unit_dirs, kind=kind, labels=labels)
