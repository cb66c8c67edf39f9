"""burrforce's own bone format, ``.bone.npz``: everything a session needs, compressed.

A NumPy ``.npz`` (a zip of ``.npy`` arrays, deflated) holding:

- ``burrforce_bone``: int64 [format version];
- ``density``, ``labels``, ``swept``: uint8 (nx, ny, nz) — the grid's three bytes per voxel;
- ``spacing_mm`` (3,), ``origin_mm`` (3,), ``direction`` (3, 3): float64 geometry;
- ``materials``: UTF-8 JSON bytes, a list of {label, name, us_n_mm2, k, forbidden};
- ``meta``: UTF-8 JSON bytes: name, format, kind, notes, bone_version, and ``generation``
  when the server saved it: the bone generation (``server/api/generation.py``) whose
  ``bone_version`` the file holds, so a client holding this file as its copy can go on with
  deltas of that generation.

Any NumPy can read it (``np.load``); mostly-empty volumes compress to a few percent.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path
from typing import BinaryIO

import numpy as np

from ...whole_files import WholeFile
from ..bone import Bone
from ..grid import BoneGrid
from ..materials import Material, MaterialTable
from .budget import require
from .errors import BoneFileError
from .npy_member import MAX_META_ELEMENTS, member_source, read_member

BONE_SUFFIX = ".bone.npz"
FORMAT_KEY = "burrforce_bone"
FORMAT_VERSION = 1


def save_bone(bone: Bone, path: str | Path, generation: int | None = None) -> Path:
    """Write ``bone`` to ``path`` (``.bone.npz`` is appended if missing). The file appears
    whole or not at all (``whole_files.WholeFile``: a full disk raises ``DiskFull`` and
    leaves nothing). ``generation``: the server's bone generation, kept in ``meta``
    (omitted when None)."""
    path = Path(path)
    if not path.name.lower().endswith(BONE_SUFFIX):
        path = path.with_name(path.name + BONE_SUFFIX)
    with WholeFile(path) as f:
        write_bone(bone, f, generation)
    return path


def write_bone(bone: Bone, f: BinaryIO, generation: int | None = None) -> None:
    """Write ``bone`` as a ``.bone.npz`` to the open binary file ``f`` (see
    :func:`save_bone`)."""
    grid = bone.grid
    materials = [{"label": label, "name": m.name, "us_n_mm2": m.us_n_mm2, "k": m.k,
                  "forbidden": m.forbidden} for label, m in bone.materials]
    meta = {"name": bone.name, "format": bone.format, "kind": bone.kind,
            "notes": bone.notes, "bone_version": grid.version}
    if generation is not None:
        meta["generation"] = int(generation)
    np.savez_compressed(
        f,
        **{FORMAT_KEY: np.array([FORMAT_VERSION], dtype=np.int64)},
        density=grid.density, labels=grid.labels, swept=grid.swept,
        spacing_mm=grid.spacing_mm, origin_mm=grid.origin_mm,
        direction=grid.direction,
        materials=_json_bytes(materials), meta=_json_bytes(meta))


def is_compact(archive: zipfile.ZipFile) -> bool:
    return FORMAT_KEY + ".npy" in archive.namelist()


def read_compact(path: Path, archive: zipfile.ZipFile, max_voxels: int,
                 memory_budget_bytes: int | None = None) -> Bone:
    """A bone from an open ``.bone.npz``. Its arrays are the bone's own: the budget is
    checked for them before they are read (``budget.require``)."""
    version = read_member(path, archive, FORMAT_KEY, 16)
    if version.shape != (1,) or int(version[0]) != FORMAT_VERSION:
        raise BoneFileError(path, f"format version {version.tolist()} is not "
                                  f"{FORMAT_VERSION}: written by another burrforce")
    missing = {k + ".npy" for k in ("density", "labels", "swept", "spacing_mm", "origin_mm",
                                    "direction", "materials", "meta")} - set(archive.namelist())
    if missing:
        raise BoneFileError(path, f"missing arrays: {sorted(m[:-4] for m in missing)}")
    require(path, member_source(path, archive, "density", max_voxels).shape,
            memory_budget_bytes)
    arrays = {k: read_member(path, archive, k, max_voxels)
              for k in ("density", "labels", "swept")}
    meta_arrays = {k: read_member(path, archive, k, MAX_META_ELEMENTS)
                   for k in ("spacing_mm", "origin_mm", "direction", "materials", "meta")}
    try:
        materials = json.loads(_text(meta_arrays["materials"]))
        meta = json.loads(_text(meta_arrays["meta"]))
        table = MaterialTable({int(m["label"]): Material(m["name"], m["us_n_mm2"], m["k"],
                                                         m["forbidden"])
                               for m in materials})
        grid = BoneGrid(arrays["density"], meta_arrays["spacing_mm"],
                        origin_mm=meta_arrays["origin_mm"], direction=meta_arrays["direction"],
                        labels=arrays["labels"], swept=arrays["swept"])
        grid.version = int(meta.get("bone_version", 0))
        _stamp_carved_bricks(grid)
        notes = [str(n) for n in meta.get("notes", [])]
    except (ValueError, TypeError, KeyError) as exc:  # JSONDecodeError is a ValueError
        raise BoneFileError(path, f"not a valid burrforce bone: {exc}") from None
    return Bone(grid, table, name=str(meta.get("name") or path), format="bone",
                kind=str(meta.get("kind", "")), notes=notes)


def _json_bytes(value: object) -> np.ndarray:
    return np.frombuffer(json.dumps(value).encode("utf-8"), dtype=np.uint8)


def _text(array: np.ndarray) -> str:
    if array.dtype != np.uint8 or array.ndim != 1:
        raise ValueError("metadata must be UTF-8 bytes")
    return array.tobytes().decode("utf-8")


def _stamp_carved_bricks(grid: BoneGrid) -> None:
    """Bricks holding carved bone get the bone's version, so "the bricks changed since version
    0" (deltas) covers the carving a restored bone arrived with."""
    if grid.version == 0:
        return
    from ..bricks import BRICK

    nb = grid.brick_version.shape
    carved = np.zeros(tuple(n * BRICK for n in nb), dtype=bool)
    nx, ny, nz = grid.shape
    carved[:nx, :ny, :nz] = (grid.swept != 0) & (grid.density != 0)
    hit = carved.reshape(nb[0], BRICK, nb[1], BRICK, nb[2], BRICK).any(axis=(1, 3, 5))
    grid.brick_version[hit] = grid.version
