"""The mesh-chunk message (``proto/MESH.md``): encoding and decoding.

The server's per-chunk surface meshes of a carved bone, for an engine to draw. The format is
a fixed little-endian binary layout (not msgpack) so that every engine reads it with its own
byte buffer type, and big meshes cost no per-element framing.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

MAGIC = b"BFMC"
#: The newest format: version 2 adds the bone generation after version 1's header. A server
#: answers version 1 unless the client asks for 2 (``format_version=2``), so readers that know
#: only 1 keep working.
FORMAT_VERSION = 2
FORMAT_VERSIONS = (1, 2)
MEDIA_TYPE = "application/vnd.burrforce.mesh-chunks"

FLAG_MORE = 1
FLAG_FULL = 2
FLAG_CW = 4
FLAG_SESSION_FRAME = 8

#: magic, format_version, flags, session, chunk_cells, bone_version, since, next_cursor,
#: chunk_count.
HEADER = struct.Struct("<4sHHIIQQII")
#: chunk index (a, b, c), vertex_count, triangle_count.
CHUNK_HEAD = struct.Struct("<3iII")
#: Version 2's header is version 1's followed by the bone generation (u64).
GENERATION = struct.Struct("<Q")
assert HEADER.size == 40 and CHUNK_HEAD.size == 20


def header_size(format_version: int) -> int:
    """The header's size, bytes: 40 (version 1) or 48 (version 2)."""
    return HEADER.size + (GENERATION.size if format_version >= 2 else 0)


@dataclass
class Chunk:
    """One chunk's surface.

    Attributes:
        index: chunk index (a, b, c).
        positions: (V, 3) float32, L (session frame) or mm (server frame).
        normals: (V, 3) float32 unit vectors out of the bone.
        materials: (V,) uint8 material labels.
        triangles: (T, 3) uint32 vertex indices.
    """

    index: tuple[int, int, int]
    positions: np.ndarray
    normals: np.ndarray
    materials: np.ndarray
    triangles: np.ndarray

    @property
    def empty(self) -> bool:
        """No surface: remove the chunk."""
        return len(self.triangles) == 0

    def nbytes(self) -> int:
        v, t = len(self.positions), len(self.triangles)
        return CHUNK_HEAD.size + 25 * v + _pad(v) + 12 * t


@dataclass
class MeshMessage:
    """A decoded message: header fields and its chunks.

    ``generation``: the bone generation the chunks are of; None in a version 1 message
    (:func:`encode` writes version 2 exactly when it is set)."""

    session: int
    chunk_cells: int
    bone_version: int
    since: int
    flags: int
    next_cursor: int = 0
    chunks: list[Chunk] = field(default_factory=list)
    generation: int | None = None

    @property
    def format_version(self) -> int:
        return 1 if self.generation is None else 2

    @property
    def more(self) -> bool:
        return bool(self.flags & FLAG_MORE)

    @property
    def full(self) -> bool:
        return bool(self.flags & FLAG_FULL)


def _pad(vertex_count: int) -> int:
    """Zero bytes after the materials so the triangles start 4-byte aligned."""
    return (-(CHUNK_HEAD.size + 25 * vertex_count)) % 4


def encode(m: MeshMessage) -> bytes:
    """``m`` as one message (header, then each chunk): version 2 when ``m.generation`` is
    set, else version 1."""
    parts = [HEADER.pack(MAGIC, m.format_version, m.flags, m.session, m.chunk_cells,
                         m.bone_version, m.since, m.next_cursor, len(m.chunks))]
    if m.generation is not None:
        parts.append(GENERATION.pack(m.generation))
    for c in m.chunks:
        v, t = len(c.positions), len(c.triangles)
        parts.append(CHUNK_HEAD.pack(*c.index, v, t))
        parts.append(np.ascontiguousarray(c.positions, dtype="<f4").tobytes())
        parts.append(np.ascontiguousarray(c.normals, dtype="<f4").tobytes())
        parts.append(np.ascontiguousarray(c.materials, dtype=np.uint8).tobytes())
        parts.append(bytes(_pad(v)))
        parts.append(np.ascontiguousarray(c.triangles, dtype="<u4").tobytes())
    return b"".join(parts)


def decode(data: bytes) -> MeshMessage:
    """A message → :class:`MeshMessage` (arrays are copies).

    Raises:
        ValueError: not this format or version, a count that overruns the bytes, an index
            past a chunk's vertices, or trailing bytes.
    """
    if len(data) < HEADER.size:
        raise ValueError(f"a mesh-chunk message is at least {HEADER.size} bytes, got "
                         f"{len(data)}")
    magic, version, flags, session, cells, bone_version, since, cursor, count = \
        HEADER.unpack_from(data)
    if magic != MAGIC:
        raise ValueError(f"not a mesh-chunk message (magic {magic!r})")
    if version not in FORMAT_VERSIONS:
        raise ValueError(f"mesh-chunk format_version {version} is not supported (this reader "
                         f"knows {', '.join(map(str, FORMAT_VERSIONS))})")
    out = MeshMessage(session, cells, bone_version, since, flags, cursor)
    at = header_size(version)
    if len(data) < at:
        raise ValueError(f"a version {version} mesh-chunk message is at least {at} bytes, "
                         f"got {len(data)}")
    if version >= 2:
        (out.generation,) = GENERATION.unpack_from(data, HEADER.size)
    for _ in range(count):
        if len(data) - at < CHUNK_HEAD.size:
            raise ValueError("the message ends inside a chunk header")
        a, b, c, v, t = CHUNK_HEAD.unpack_from(data, at)
        size = CHUNK_HEAD.size + 25 * v + _pad(v) + 12 * t
        if len(data) - at < size:
            raise ValueError(f"chunk ({a}, {b}, {c}) claims {v} vertices and {t} triangles: "
                             "more than the bytes left")
        p = at + CHUNK_HEAD.size
        positions = np.frombuffer(data, "<f4", 3 * v, p).reshape(v, 3).astype(np.float32)
        p += 12 * v
        normals = np.frombuffer(data, "<f4", 3 * v, p).reshape(v, 3).astype(np.float32)
        p += 12 * v
        materials = np.frombuffer(data, np.uint8, v, p).copy()
        p += v + _pad(v)
        triangles = np.frombuffer(data, "<u4", 3 * t, p).reshape(t, 3).astype(np.uint32)
        if v and not t:
            raise ValueError(f"chunk ({a}, {b}, {c}) has {v} vertices and no triangles")
        if t and int(triangles.max()) >= v:
            raise ValueError(f"chunk ({a}, {b}, {c}) has a triangle index past its {v} "
                             "vertices")
        out.chunks.append(Chunk((a, b, c), positions, normals, materials, triangles))
        at += size
    if at != len(data):
        raise ValueError(f"{len(data) - at} bytes after the last chunk")
    return out
