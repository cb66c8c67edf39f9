"""Surface meshes of a (carved) bone by marching cubes, and STL, PLY and OBJ writers.

:func:`surface_mesh` extracts the iso-surface of the remaining bone fraction
(``remaining_density() / 255``) with scikit-image's Lewiner marching cubes, in the world frame
(mm), closed (the volume is padded with empty voxels, so bone touching the grid's edge or a
crop gets a cap) and oriented: faces are counter-clockwise seen from outside the bone and the
normals point out of it, so the signed volume of the mesh is the bone's volume.

The writers (:func:`write_stl`, :func:`write_ply`, :func:`write_obj`, and ``MESH_FORMATS`` by
name) are plain numpy: vectorised, a chunk of faces at a time into any binary file object.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np
from skimage.measure import marching_cubes

from .export import remaining_of
from .grid import BoneGrid
from .materials import N_LABELS

#: The most faces :func:`surface_mesh` returns by default (≈ 700 MB of mesh and temporaries).
MAX_FACES = 20_000_000
#: Faces (or vertices) formatted and written per chunk.
CHUNK = 1 << 18
#: Voxels converted per chunk while the marching-cubes volume is filled.
_FILL_CHUNK = 1 << 22

Box = tuple[Sequence[float], Sequence[float]]


@dataclass
class Mesh:
    """A triangle mesh in the world frame.

    Attributes
    ----------
    vertices_mm : np.ndarray
        (n, 3) float32 vertex positions, world frame, mm (LPS for loaded scans).
    faces : np.ndarray
        (m, 3) int32 vertex indices (0-based), counter-clockwise seen from outside the bone
        (the right-hand normal points out of it).
    normals : np.ndarray
        (n, 3) float32 unit vertex normals pointing out of the bone: the area-weighted mean of
        the adjoining faces' normals.
    """

    vertices_mm: np.ndarray
    faces: np.ndarray
    normals: np.ndarray

    @property
    def n_vertices(self) -> int:
        return int(self.vertices_mm.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def face_normals(self) -> np.ndarray:
        """(m, 3) float32 unit normals of the faces by their winding (zero for a face of no
        area)."""
        return _face_normals(self.vertices_mm, self.faces)

    def volume_mm3(self) -> float:
        """The signed volume enclosed by the mesh, mm³ (positive when closed and oriented
        outwards: then the volume inside the surface)."""
        v = self.vertices_mm.astype(np.float64)
        # Relative to the centroid: the same for a closed mesh, less round-off.
        if len(v):
            v = v - v.mean(axis=0)
        total = 0.0
        for s in range(0, self.n_faces, CHUNK):
            f = self.faces[s:s + CHUNK]
            a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
            total += float(np.einsum("ij,ij->", a, np.cross(b, c)))
        return total / 6.0

    def area_mm2(self) -> float:
        """Total face area, mm²."""
        v = self.vertices_mm.astype(np.float64)
        total = 0.0
        for s in range(0, self.n_faces, CHUNK):
            f = self.faces[s:s + CHUNK]
            cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
            total += float(np.linalg.norm(cross, axis=1).sum())
        return 0.5 * total


def empty_mesh() -> Mesh:
    """A mesh with no vertices and no faces."""
    return Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32),
                np.zeros((0, 3), np.float32))


def surface_mesh(
    grid: BoneGrid,
    level: float = 0.5,
    step: int = 1,
    labels: Sequence[int] | np.ndarray | None = None,
    region_mm: Box | None = None,
    max_faces: int = MAX_FACES,
) -> Mesh:
    """The bone's surface: the iso-surface of its remaining fraction, by marching cubes.

    Parameters
    ----------
    grid : BoneGrid
        The bone (nx, ny, nz voxels); read, never written.
    level : float
        Iso-value of the remaining bone fraction ``remaining_density() / 255``, in (0, 1).
        0.5 puts the surface where voxels are half bone (partial volume makes that sub-voxel
        accurate).
    step : int
        Marching-cubes step, voxels (≥ 1): 2 samples every other voxel, for about 4× fewer
        faces and a coarser surface.
    labels : sequence of int, optional
        Only voxels carrying one of these material labels count as bone (e.g. ``[3]`` for the
        temporal phantom's nerve; an empty sequence gives an empty mesh). Default: every
        voxel. Partial volume is kept only where the selection borders empty space: against
        other materials the surface runs on voxel faces.
    region_mm : (lo, hi), optional
        Crop to the world-frame box ``lo`` ≤ x ≤ ``hi`` (two 3-vectors, mm): the voxels whose
        centres lie inside it (for an oblique grid: inside the box's bounding box along the
        grid's axes). Bone cut by the crop is capped, so the mesh stays closed.
    max_faces : int
        Refuse meshes with more faces (checked on an estimate before marching cubes runs,
        and on the result).

    Returns
    -------
    Mesh
        Vertices (n, 3) float32 in the world frame, mm; faces (m, 3) int32, counter-clockwise
        seen from outside; outward unit normals (n, 3) float32. No bone in the (cropped,
        filtered) volume gives a mesh with 0 faces.

    Raises
    ------
    ValueError
        ``level`` not in (0, 1), ``step`` not a positive integer, a label outside 0..255, a
        malformed region, or more than ``max_faces`` faces (the message suggests a larger
        ``step`` or a ``region_mm``).

    Notes
    -----
    Memory: a float32 copy of the cropped volume (4 bytes per voxel: 537 MB for a whole 512³
    grid, hence ``region_mm``), plus the mesh (≈ 60 bytes per face with marching cubes'
    temporaries). The face estimate (twice the sample edges the surface crosses) is within
    0.1 % on the phantoms; a mesh just under ``max_faces`` may be refused on it. Time: the
    temporal phantom at 0.2 mm (4.8 M voxels, 216 k faces) takes ≈ 0.25 s.
    """
    level = _level(level)
    step = _positive_int("step", step)
    max_faces = _positive_int("max_faces", max_faces, minimum=0)
    lut = _label_lut(labels)
    crop = _crop(grid, region_mm)
    if crop is None:
        return empty_mesh()
    volume, offset = _fill(grid, crop, lut, step)
    threshold = np.float32(level * 255.0)
    if not volume.max() > threshold:
        return empty_mesh()
    estimate = _estimate_faces(volume, threshold, step)
    if estimate > max_faces:
        raise ValueError(_too_many(estimate, max_faces, step, "about "))
    # "ascent": the MC's own winding, which with the (i, j, k) vertex order it returns is
    # counter-clockwise seen from the low side (outside the bone).
    verts, faces, normals, _ = marching_cubes(volume, float(threshold), step_size=step,
                                              gradient_direction="ascent")
    if len(faces) > max_faces:
        raise ValueError(_too_many(len(faces), max_faces, step, ""))
    return _to_world(grid, verts, faces, normals, offset)


def _level(level: object) -> float:
    if isinstance(level, bool) or not isinstance(level, (int, float, np.integer, np.floating)) \
            or not 0.0 < float(level) < 1.0:
        raise ValueError(f"level must be a bone fraction strictly between 0 and 1, got "
                         f"{level!r}")
    return float(level)


def _positive_int(name: str, value: object, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) \
            or int(value) < minimum:
        raise ValueError(f"{name} must be an integer ≥ {minimum}, got {value!r}")
    return int(value)


def _label_lut(labels: Sequence[int] | np.ndarray | None) -> np.ndarray | None:
    """(256,) bool: which labels count as bone, or None for all."""
    if labels is None:
        return None
    try:
        if isinstance(labels, (str, bytes)):
            raise TypeError
        items = np.asarray(labels).reshape(-1).tolist() if isinstance(labels, np.ndarray) \
            else list(labels)
    except TypeError:
        raise ValueError(f"labels must be a sequence of material labels, got {labels!r}") \
            from None
    lut = np.zeros(N_LABELS, dtype=bool)
    for label in items:
        if isinstance(label, bool) or not isinstance(label, (int, np.integer)) \
                or not 0 <= int(label) < N_LABELS:
            raise ValueError(f"labels must be integers in 0..{N_LABELS - 1}, got {label!r}")
        lut[int(label)] = True
    return lut


def _crop(grid: BoneGrid, region_mm: Box | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Inclusive voxel index range (first (3,), last (3,)) inside ``region_mm``; None if no
    voxel centre is inside it."""
    shape = np.asarray(grid.shape)
    if region_mm is None:
        return np.zeros(3, dtype=np.int64), shape - 1
    try:
        lo, hi = (np.asarray(x, dtype=np.float64) for x in region_mm)
    except (TypeError, ValueError):
        raise ValueError(f"region_mm must be (lo, hi), two 3-vectors in mm, got "
                         f"{region_mm!r}") from None
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo) & np.isfinite(hi)).all():
        raise ValueError(f"region_mm must be (lo, hi), two finite 3-vectors in mm, got "
                         f"{region_mm!r}")
    if not (lo <= hi).all():
        raise ValueError(f"region_mm needs lo ≤ hi on every axis, got {lo.tolist()} and "
                         f"{hi.tolist()}")
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    index = ((corners - grid.origin_mm) @ grid.direction) / grid.spacing_mm
    eps = 1e-9  # a box edge exactly on a voxel centre keeps that voxel despite round-off
    first = np.maximum(np.ceil(index.min(axis=0) - eps), 0).astype(np.int64)
    last = np.minimum(np.floor(index.max(axis=0) + eps), shape - 1).astype(np.int64)
    if (first > last).any():
        return None
    return first, last


def _fill(grid: BoneGrid, crop: tuple[np.ndarray, np.ndarray], lut: np.ndarray | None,
          step: int) -> tuple[np.ndarray, np.ndarray]:
    """The cropped remaining density (0–255, float32) in a zero border: one voxel before and
    enough after that the last marching-cubes sample (a multiple of ``step``) is empty too.

    Returns the volume and the grid index of its element (0, 0, 0) (float64 (3,))."""
    first, last = crop
    n = last - first + 1
    # Data at padded indices 1..n; samples at 0, step, …, N − 1 with N − 1 ≥ n + 1.
    size = step * np.ceil((n + 1) / step).astype(np.int64) + 1
    volume = np.zeros(tuple(int(s) for s in size), dtype=np.float32)
    per = max(1, _FILL_CHUNK // int(n[1] * n[2]))
    j = slice(int(first[1]), int(last[1]) + 1)
    k = slice(int(first[2]), int(last[2]) + 1)
    for i0 in range(int(first[0]), int(last[0]) + 1, per):
        i = slice(i0, min(i0 + per, int(last[0]) + 1))
        block = remaining_of(grid.density[i, j, k], grid.swept[i, j, k])
        if lut is not None:
            block[~lut[grid.labels[i, j, k]]] = 0
        a = i0 - int(first[0]) + 1
        volume[a:a + block.shape[0], 1:1 + int(n[1]), 1:1 + int(n[2])] = block
    return volume, first.astype(np.float64) - 1.0


def _estimate_faces(volume: np.ndarray, threshold: np.float32, step: int) -> int:
    """Faces marching cubes will make, about: twice the sample edges the surface crosses (one
    vertex each; a closed triangle mesh has about twice as many faces as vertices)."""
    inside = volume[::step, ::step, ::step] > threshold
    edges = sum(int(np.count_nonzero(np.diff(inside, axis=a))) for a in range(3))
    return 2 * edges


def _too_many(faces: int, max_faces: int, step: int, about: str) -> str:
    suggest = max(step + 1, math.ceil(step * math.sqrt(faces / max(max_faces, 1))))
    return (f"the surface has {about}{faces:,} faces, more than max_faces = {max_faces:,}: use "
            f"a larger step (faces fall as 1/step²; try step={suggest}) or a region_mm around "
            "the part you need")


def _to_world(grid: BoneGrid, verts: np.ndarray, faces: np.ndarray, normals: np.ndarray,
              offset: np.ndarray) -> Mesh:
    """Marching-cubes output (padded-volume indices) → a world-frame :class:`Mesh`."""
    scale = grid.spacing_mm
    rot = grid.direction
    points = (verts.astype(np.float64) + offset) * scale  # grid frame, mm
    world = (grid.origin_mm + points @ rot.T).astype(np.float32)
    faces = np.ascontiguousarray(faces, dtype=np.int32)
    # Vertex normals from the faces: on partial-volume data they follow the surface better
    # than marching cubes' own gradient normals (a 4 mm sphere in 0.25 mm voxels: at worst
    # 10° off the radius against 31°), and they agree with the winding by construction.
    n = vertex_normals(world, faces)
    bad = ~(np.linalg.norm(n, axis=1) > 0.0)
    if bad.any():  # a vertex of degenerate faces only: the field's gradient (index units → mm)
        g = (normals[bad].astype(np.float64) / scale) @ rot.T
        length = np.linalg.norm(g, axis=1, keepdims=True)
        n[bad] = np.divide(g, length, out=np.zeros_like(g), where=length > 0.0)
    return Mesh(world, faces, n.astype(np.float32))


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) float32 unit normals by winding; zero for faces of no area."""
    v = vertices.astype(np.float64, copy=False)
    cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    length = np.linalg.norm(cross, axis=1, keepdims=True)
    np.divide(cross, length, out=cross, where=length > 0.0)
    cross[length[:, 0] == 0.0] = 0.0
    return cross.astype(np.float32)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) float64 unit area-weighted vertex normals by winding (zero for a vertex of no
    area)."""
    v = vertices.astype(np.float64)
    cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    out = np.zeros_like(v)
    for c in range(3):
        for corner in range(3):
            out[:, c] += np.bincount(faces[:, corner], cross[:, c], minlength=len(v))
    length = np.linalg.norm(out, axis=1, keepdims=True)
    np.divide(out, length, out=out, where=length > 0.0)
    return out


# -- writers ----------------------------------------------------------------------------------
#: One binary STL facet: normal, three vertices, attribute byte count (50 bytes, packed).
STL_FACET = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)),
                      ("attribute", "<u2")])
#: One binary PLY face: a uchar count (3) and three little-endian int32 indices (13 bytes).
PLY_FACE = np.dtype([("count", "u1"), ("indices", "<i4", (3,))])


def _check_mesh(mesh: Mesh) -> None:
    if mesh.vertices_mm.ndim != 2 or mesh.vertices_mm.shape[1] != 3 \
            or mesh.normals.shape != mesh.vertices_mm.shape \
            or mesh.faces.ndim != 2 or mesh.faces.shape[1] != 3:
        raise ValueError(f"a mesh needs (n, 3) vertices and normals and (m, 3) faces, got "
                         f"{mesh.vertices_mm.shape}, {mesh.normals.shape} and "
                         f"{mesh.faces.shape}")
    if mesh.n_faces and (int(mesh.faces.min()) < 0 or int(mesh.faces.max()) >= mesh.n_vertices):
        raise ValueError("a face indexes a vertex the mesh does not have")


def write_stl(mesh: Mesh, f: BinaryIO) -> None:
    """Binary STL: an 80-byte header, uint32 facet count, then per facet its unit normal
    (from the winding), three vertices (float32 little-endian, mm) and a zero uint16.

    Parameters
    ----------
    mesh : Mesh
        The mesh (world frame, mm). STL keeps no vertex sharing and no vertex normals.
    f : BinaryIO
        Where to write; 84 + 50·m bytes.
    """
    _check_mesh(mesh)
    if mesh.n_faces >= 2**32:
        raise ValueError(f"binary STL holds fewer than 2³² facets, the mesh has {mesh.n_faces}")
    f.write(b"burrforce bone surface, mm, world frame".ljust(80, b" "))
    f.write(struct.pack("<I", mesh.n_faces))
    for s in range(0, mesh.n_faces, CHUNK):
        faces = mesh.faces[s:s + CHUNK]
        out = np.zeros(len(faces), dtype=STL_FACET)
        out["normal"] = _face_normals(mesh.vertices_mm, faces)
        out["vertices"] = mesh.vertices_mm[faces]
        f.write(out.tobytes())


def write_ply(mesh: Mesh, f: BinaryIO) -> None:
    """Binary little-endian PLY: vertices with their normals (float32 x, y, z, nx, ny, nz),
    faces as ``list uchar int vertex_indices`` (0-based).

    Parameters
    ----------
    mesh : Mesh
        The mesh (world frame, mm).
    f : BinaryIO
        Where to write: an ASCII header, then 24·n + 13·m bytes.
    """
    _check_mesh(mesh)
    header = "\n".join([
        "ply",
        "format binary_little_endian 1.0",
        "comment burrforce bone surface, world frame, mm",
        f"element vertex {mesh.n_vertices}",
        *(f"property float {name}" for name in ("x", "y", "z", "nx", "ny", "nz")),
        f"element face {mesh.n_faces}",
        "property list uchar int vertex_indices",
        "end_header",
    ]) + "\n"
    f.write(header.encode("ascii"))
    for s in range(0, mesh.n_vertices, CHUNK):
        block = np.concatenate([mesh.vertices_mm[s:s + CHUNK], mesh.normals[s:s + CHUNK]],
                               axis=1)
        f.write(block.astype("<f4").tobytes())
    for s in range(0, mesh.n_faces, CHUNK):
        faces = mesh.faces[s:s + CHUNK]
        out = np.empty(len(faces), dtype=PLY_FACE)
        out["count"] = 3
        out["indices"] = faces
        f.write(out.tobytes())


def write_obj(mesh: Mesh, f: BinaryIO) -> None:
    """Text Wavefront OBJ: ``v x y z`` (mm), ``vn nx ny nz``, ``f a//a b//b c//c`` (1-based;
    each vertex's normal has its index), ASCII with ``\\n`` line ends.

    Parameters
    ----------
    mesh : Mesh
        The mesh (world frame, mm). Vertices are written with 9 significant digits (float32
        reads back exactly), normals with 6.
    f : BinaryIO
        Where to write (bytes).
    """
    _check_mesh(mesh)
    f.write(f"# burrforce bone surface, world frame, mm: {mesh.n_vertices} vertices, "
            f"{mesh.n_faces} faces\n".encode("ascii"))
    for rows, line in ((mesh.vertices_mm, "v %.9g %.9g %.9g\n"),
                       (mesh.normals, "vn %.6g %.6g %.6g\n")):
        for s in range(0, len(rows), CHUNK):
            block = rows[s:s + CHUNK]
            f.write(((line * len(block)) % tuple(block.ravel().tolist())).encode("ascii"))
    for s in range(0, mesh.n_faces, CHUNK):
        block = np.repeat(mesh.faces[s:s + CHUNK].astype(np.int64) + 1, 2, axis=1)
        text = ("f %d//%d %d//%d %d//%d\n" * len(block)) % tuple(block.ravel().tolist())
        f.write(text.encode("ascii"))


MeshWriter = Callable[[Mesh, BinaryIO], None]
#: Mesh format → (writer, media type, file suffix), for an HTTP layer. PLY has no registered
#: media type: ``application/x-ply`` is the customary one.
MESH_FORMATS: dict[str, tuple[MeshWriter, str, str]] = {
    "stl": (write_stl, "model/stl", ".stl"),
    "ply": (write_ply, "application/x-ply", ".ply"),
    "obj": (write_obj, "model/obj", ".obj"),
}
