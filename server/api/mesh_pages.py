"""Mesh-chunk messages for a session (``proto/MESH.md``): which chunks, in which frame and
winding, cut into pages of a byte budget."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...proto import frames
from ...proto.mesh_chunks import (
    FLAG_CW,
    FLAG_FULL,
    FLAG_MORE,
    FLAG_SESSION_FRAME,
    Chunk,
    MeshMessage,
    header_size,
)
from ..bone.chunks import (
    CHUNK_BRICKS_DEFAULT,
    changed_chunks,
    chunk_cells,
    chunk_shape,
    mesh_chunk,
    ordinals,
    surface_chunks,
)
from ..bone.grid import BoneGrid

MAX_BYTES_DEFAULT = 4 << 20
MAX_BYTES_MIN = 64 << 10
MAX_BYTES_MAX = 64 << 20


@dataclass(frozen=True)
class MeshRequest:
    """What a client asked for.

    Attributes:
        session: the session id (echoed in the header).
        chunk_bricks: chunk edge in bricks (1–8).
        session_frame: positions in the session's frame and unit (else server frame, mm).
        cw: triangles wound so the right-handed cross product points into the bone.
        frame_name, placement_position, placement_orientation: the session's frame.
    """

    session: int
    chunk_bricks: int = CHUNK_BRICKS_DEFAULT
    session_frame: bool = True
    cw: bool = False
    frame_name: str = frames.DEFAULT_FRAME
    placement_position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    placement_orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)

    def __post_init__(self) -> None:
        chunk_cells(self.chunk_bricks)  # raises ValueError when out of range


class ChunkTransform:
    """Grid-index coordinates → the output frame, vectorized: ``out = Aᵀ·(i·spacing − b)/s``
    with the session's :class:`~burrforce.proto.frames.Transform` aimed at the grid."""

    def __init__(self, grid: BoneGrid, req: MeshRequest) -> None:
        if req.session_frame:
            tf = frames.Transform(frames.frame(req.frame_name), req.placement_position,
                                  req.placement_orientation, grid.direction, grid.origin_mm)
        else:
            tf = frames.Transform(frames.frame(frames.DEFAULT_FRAME),
                                  target_rotation=grid.direction,
                                  target_origin_mm=grid.origin_mm)
        self.spacing = grid.spacing_mm
        self.a = tf.matrix
        self.offset = tf.offset_mm
        self.scale = tf.scale
        # Reverse the index order when exactly one of (a reflection, cw asked) holds.
        self.reverse = (tf.det < 0) != req.cw

    def chunk(self, index: tuple[int, int, int], points: np.ndarray, normals: np.ndarray,
              materials: np.ndarray, triangles: np.ndarray) -> Chunk:
        pos = ((points * self.spacing - self.offset) @ self.a) / self.scale
        nrm = normals @ self.a
        tri = triangles[:, ::-1] if self.reverse else triangles
        pos32 = pos.astype(np.float32)
        if not np.isfinite(pos32).all():
            raise ValueError("the session's placement puts the bone beyond float32 range in "
                             "its frame: move it nearer the engine's origin")
        return Chunk(index, pos32, nrm.astype(np.float32),
                     materials.astype(np.uint8), np.ascontiguousarray(tri, dtype=np.uint32))


def mesh_page(grid: BoneGrid, req: MeshRequest, since: int | None, cursor: int = 0,
              max_bytes: int = MAX_BYTES_DEFAULT,
              generation: int | None = None) -> MeshMessage:
    """One page: the chunks changed after bone version ``since`` (every chunk with surface
    when ``since`` is None or newer than the bone), from chunk number ``cursor`` on, until
    ``max_bytes`` is reached (at least one chunk). ``generation``: the bone's generation,
    for a format version 2 message (None: version 1). The caller turns a client's copy of
    another generation into ``since=None``.

    Raises:
        ValueError: a negative ``since`` or ``cursor``, or ``max_bytes`` out of range.
    """
    if (since is not None and since < 0) or cursor < 0:
        raise ValueError("since and cursor must be ≥ 0")
    if not MAX_BYTES_MIN <= max_bytes <= MAX_BYTES_MAX:
        raise ValueError(f"max_bytes must be in {MAX_BYTES_MIN}..{MAX_BYTES_MAX}")
    version = int(grid.version)  # before the stamps: a chunk changed later is sent again
    cells = chunk_cells(req.chunk_bricks)
    shape = chunk_shape(grid.shape, cells)
    full = since is None or since > version
    todo = surface_chunks(grid, cells) if full else changed_chunks(grid, int(since), cells)
    numbers = ordinals(todo, shape)
    keep = numbers >= cursor
    todo, numbers = todo[keep], numbers[keep]
    flags = (FLAG_CW if req.cw else 0) | (FLAG_SESSION_FRAME if req.session_frame else 0)
    if full and cursor == 0:
        flags |= FLAG_FULL
    out = MeshMessage(req.session, cells, version, 0 if full else int(since), flags,
                      generation=generation)
    tf = ChunkTransform(grid, req)
    size = header_size(out.format_version)
    for n, index in enumerate(todo):
        s = mesh_chunk(grid, tuple(int(x) for x in index), cells)
        if full and not len(s.triangles):
            continue  # a full answer lists what exists; nothing to remove
        c = tf.chunk(s.index, s.points, s.normals, s.materials, s.triangles)
        out.chunks.append(c)
        size += c.nbytes()
        if size >= max_bytes and n + 1 < len(todo):
            out.flags |= FLAG_MORE
            out.next_cursor = int(numbers[n]) + 1
            break
    return out
