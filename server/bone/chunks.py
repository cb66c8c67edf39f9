"""The carved bone's surface cut into chunks (``proto/MESH.md`` §1), for engines to draw.

Marching cubes runs on the remaining density (0–255, iso-level 127.5) between voxel centres,
with the empty layer around the grid that :func:`.mesh.surface_mesh` adds, so the union of
every chunk's triangles is the full export's surface, triangle for triangle. A chunk owns
``C = 8·chunk_bricks`` cells per axis: chunk ``a`` the cells whose first sample lies in
``[a·C − 1, (a+1)·C − 1)`` (sample −1 is the empty layer). A brick's voxel change touches the
cells on both sides of each voxel, so brick ``b`` dirties chunks ``⌊8b/C⌋ … ⌊(8b+8)/C⌋``.

Seams agree because everything at a vertex comes from global samples: its position from the
two samples of its cell edge, its normal from central differences on the global grid (a
block one sample wider than the chunk on every side), its material from the inside sample.

Pure functions over a :class:`~.grid.BoneGrid`: positions are grid-index coordinates here;
the caller turns them into the engine's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.measure import marching_cubes

from .bricks import BRICK
from .export import remaining_of
from .grid import BoneGrid
from .mesh import vertex_normals

#: Iso-level of the remaining density: half bone, as the full export's level 0.5.
LEVEL = 127.5
CHUNK_BRICKS_MAX = 8
#: The default: the smallest updates while cutting (benchmarks/mesh.md).
CHUNK_BRICKS_DEFAULT = 2


@dataclass
class ChunkSurface:
    """One chunk's surface in grid-index coordinates.

    Attributes:
        index: chunk index (a, b, c).
        points: (V, 3) float64 sample-index coordinates (voxel (i, j, k)'s centre is
            (i, j, k)).
        normals: (V, 3) float64 unit normals out of the bone, on the grid's axes.
        materials: (V,) uint8 labels.
        triangles: (T, 3) int64, counter-clockwise seen from outside in index coordinates.
    """

    index: tuple[int, int, int]
    points: np.ndarray
    normals: np.ndarray
    materials: np.ndarray
    triangles: np.ndarray


def chunk_cells(chunk_bricks: int) -> int:
    """Cells per chunk edge for ``chunk_bricks`` (1–8)."""
    if isinstance(chunk_bricks, bool) or not isinstance(chunk_bricks, (int, np.integer)) \
            or not 1 <= int(chunk_bricks) <= CHUNK_BRICKS_MAX:
        raise ValueError(f"chunk_bricks must be an integer in 1..{CHUNK_BRICKS_MAX}, got "
                         f"{chunk_bricks!r}")
    return BRICK * int(chunk_bricks)


def chunk_shape(grid_shape: tuple[int, int, int], cells: int) -> tuple[int, int, int]:
    """Chunks per axis: the n voxels plus the empty layers make n + 1 cells."""
    return tuple(-(-(int(n) + 1) // cells) for n in grid_shape)  # type: ignore[return-value]


def chunks_of_bricks(bricks: np.ndarray, cells: int,
                     shape: tuple[int, int, int]) -> np.ndarray:
    """The chunks whose cells touch any voxel of ``bricks`` ((k, 3) brick indices): (m, 3)
    int64, unique, in C order."""
    bricks = np.asarray(bricks, dtype=np.int64).reshape(-1, 3)
    if not len(bricks):
        return np.zeros((0, 3), dtype=np.int64)
    top = np.asarray(shape, dtype=np.int64) - 1
    lo = np.minimum(BRICK * bricks // cells, top)
    hi = np.minimum((BRICK * bricks + BRICK) // cells, top)
    picks = [np.where(np.array([(m >> a) & 1 for a in range(3)], dtype=bool), hi, lo)
             for m in range(8)]
    return np.unique(np.concatenate(picks), axis=0)


def ordinals(index: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """C-order numbers of chunk indices (n, 3): the order chunks are sent in."""
    index = np.asarray(index, dtype=np.int64).reshape(-1, 3)
    return (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]


def surface_chunks(grid: BoneGrid, cells: int) -> np.ndarray:
    """Chunks that may hold surface: those touching a brick with bone (m, 3)."""
    return chunks_of_bricks(np.argwhere(grid.brick_bone > 0), cells,
                            chunk_shape(grid.shape, cells))


def changed_chunks(grid: BoneGrid, since_version: int, cells: int) -> np.ndarray:
    """Chunks whose surface may differ from bone version ``since_version`` (m, 3)."""
    return chunks_of_bricks(np.argwhere(grid.brick_version > since_version), cells,
                            chunk_shape(grid.shape, cells))


def _samples(grid: BoneGrid, first: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Remaining density (float32) and labels (uint8) at samples ``first + 0 … size − 1``
    per axis, (size, size, size); 0 (empty, label 0) outside the grid."""
    density = np.zeros((size, size, size), dtype=np.float32)
    labels = np.zeros((size, size, size), dtype=np.uint8)
    lo = np.maximum(first, 0)
    hi = np.minimum(first + size, np.asarray(grid.shape))
    if (hi <= lo).any():
        return density, labels
    src = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    dst = tuple(slice(int(a - f), int(b - f)) for a, b, f in zip(lo, hi, first, strict=True))
    density[dst] = remaining_of(grid.density[src], grid.swept[src])
    labels[dst] = grid.labels[src]
    return density, labels


def _trilinear(field: np.ndarray, at: np.ndarray) -> np.ndarray:
    """``field`` (n, n, n) sampled at (V, 3) float coordinates inside it: (V,)."""
    n = field.shape[0]
    base = np.clip(np.floor(at).astype(np.int64), 0, n - 2)
    t = at - base
    out = np.zeros(len(at), dtype=np.float64)
    for corner in range(8):
        d = np.array([(corner >> a) & 1 for a in range(3)])
        w = np.prod(np.where(d, t, 1.0 - t), axis=1)
        i = base + d
        out += w * field[i[:, 0], i[:, 1], i[:, 2]]
    return out


def mesh_chunk(grid: BoneGrid, index: tuple[int, int, int], cells: int) -> ChunkSurface:
    """Chunk ``index``'s surface (possibly empty)."""
    a = np.asarray(index, dtype=np.int64)
    first = a * cells - 1  # the chunk's first sample
    # One sample more on every side than the chunk's C + 1: central differences there.
    block, labels = _samples(grid, first - 1, cells + 3)
    inner = block[1:-1, 1:-1, 1:-1]
    empty = ChunkSurface(tuple(int(x) for x in a), np.zeros((0, 3)), np.zeros((0, 3)),
                         np.zeros(0, dtype=np.uint8), np.zeros((0, 3), dtype=np.int64))
    if not (inner.min() < LEVEL < inner.max()):
        return empty
    verts, faces, _, _ = marching_cubes(inner, LEVEL, gradient_direction="ascent")
    if not len(faces):
        return empty
    verts = verts.astype(np.float64)
    # Normals: −∇density (it grows into the bone), per grid axis in mm, then rotated.
    at = verts + 1.0
    gradient = np.stack([_trilinear(g, at) for g in np.gradient(block.astype(np.float64))],
                        axis=1) / grid.spacing_mm
    normals = -gradient
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    flat = length[:, 0] == 0.0
    if flat.any():  # a saddle of the field: the faces' own normals instead
        normals[flat] = vertex_normals(verts * grid.spacing_mm, faces)[flat]
        length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0.0)
    # Material: the label of the edge's end with more bone (the end inside).
    low = np.floor(verts).astype(np.int64)
    high = np.minimum(np.ceil(verts).astype(np.int64), cells)
    d_low = inner[low[:, 0], low[:, 1], low[:, 2]]
    d_high = inner[high[:, 0], high[:, 1], high[:, 2]]
    inside = np.where((d_high > d_low)[:, None], high, low) + 1
    materials = labels[inside[:, 0], inside[:, 1], inside[:, 2]]
    return ChunkSurface(tuple(int(x) for x in a), verts + first, normals, materials,
                        faces.astype(np.int64))
