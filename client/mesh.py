"""The carved bone as chunk meshes kept current on the client (``proto/MESH.md`` §4).

:class:`ChunkedMesh` applies mesh-chunk messages; :func:`sync_rest` brings one up to date over
REST, :func:`watch` follows the WebSocket push channel. The engine SDKs under ``client/`` do
the same in their own languages.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..proto.mesh_chunks import Chunk, MeshMessage, decode
from .rest import BurrRest


class ChunkedMesh:
    """Chunk index → its mesh, and the bone (generation, version) the copy is at.

    Attributes:
        chunks: chunk index (a, b, c) → :class:`~burrforce.proto.mesh_chunks.Chunk`.
        have: the bone version every chunk is at least as new as (None before the first
            complete update, and after an update that spanned two bones: ask for
            everything).
        generation: the bone generation the copy is of (None: not known, from format
            version 1 messages, or no copy yet).
        replaced: chunks replaced or removed by updates after the first, in all.
    """

    def __init__(self) -> None:
        self.chunks: dict[tuple[int, int, int], Chunk] = {}
        self.have: int | None = None
        self.generation: int | None = None
        self.replaced = 0
        self._low: int | None = None
        self._generations: set[int | None] = set()
        self._started_full = False

    def apply(self, m: MeshMessage) -> bool:
        """Apply one message; True when it completed an update (``have`` moved)."""
        if self._low is None:  # the first message of an update
            self._generations, self._started_full = set(), m.full
        self._generations.add(m.generation)
        if m.full:
            self.chunks.clear()
        for c in m.chunks:
            if self.have is not None:
                self.replaced += 1
            if c.empty:
                self.chunks.pop(c.index, None)
            else:
                self.chunks[c.index] = c
        self._low = m.bone_version if self._low is None else min(self._low, m.bone_version)
        if m.more:
            return False
        self.have, self._low = self._low, None
        (generation, *others) = self._generations
        if others or (generation is not None and not self._started_full
                      and self.generation is not None and generation != self.generation):
            # Pages of two bones, or changes of another bone on top of this copy (the bone
            # was replaced between two requests): the copy cannot be trusted; start over.
            self.have = self.generation = None
        elif generation is not None:
            self.generation = generation
        return True

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every chunk in one mesh, not welded: positions (n, 3) float32, normals (n, 3)
        float32, materials (n,) uint8, triangles (m, 3) int64."""
        chunks = [self.chunks[k] for k in sorted(self.chunks)]
        if not chunks:
            return (np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                    np.zeros(0, np.uint8), np.zeros((0, 3), np.int64))
        offsets = np.cumsum([0] + [len(c.positions) for c in chunks[:-1]])
        return (np.concatenate([c.positions for c in chunks]),
                np.concatenate([c.normals for c in chunks]),
                np.concatenate([c.materials for c in chunks]),
                np.concatenate([c.triangles.astype(np.int64) + o
                                for c, o in zip(chunks, offsets, strict=True)]))

    def write_obj(self, path: str | Path) -> Path:
        """The union of the chunks as OBJ (positions and triangles as received)."""
        positions, _, _, triangles = self.arrays()
        path = Path(path)
        with open(path, "w") as f:
            np.savetxt(f, positions, fmt="v %.9g %.9g %.9g")
            np.savetxt(f, triangles + 1, fmt="f %d %d %d")
        return path


def sync_rest(api: BurrRest, session: int, mesh: ChunkedMesh, **query: object) -> int:
    """Bring ``mesh`` up to the bone over REST (every page); returns the pages fetched.
    ``query``: chunk_bricks, frame, winding, max_bytes (proto/MESH.md §2). Asks for format
    version 2 and names the copy's generation, so a replaced bone comes back FULL."""
    cursor, pages = 0, 0
    since, generation = mesh.have, mesh.generation  # the same for every page of the update
    while True:
        params = {"format_version": 2, **query, "cursor": cursor}
        if since is not None:
            params["since"] = since
            if generation is not None:
                params["generation"] = generation
        m = decode(api.mesh_chunks(session, **params))
        pages += 1
        mesh.apply(m)
        if not m.more:
            return pages
        cursor = m.next_cursor


def watch(url: str, token: str, session: int, since: int | None = None,
          timeout_s: float = 10.0, generation: int | None = None,
          **query: object) -> Iterator[MeshMessage]:
    """The WebSocket push channel's messages, as they come (a blocking iterator; close it to
    disconnect), in format version 2 (with the bone generation) unless ``query`` says
    otherwise. ``url`` is the REST URL (``http://host:port``). Reconnecting with a copy:
    ``since=mesh.have, generation=mesh.generation`` (a replaced bone comes back FULL)."""
    from websockets.sync.client import connect

    params = {k: str(v) for k, v in {"format_version": 2, **query}.items()}
    if since is not None:
        params["since"] = str(since)
        if generation is not None:
            params["generation"] = str(generation)
    ws_url = url.rstrip("/").removesuffix("/v1").replace("http", "ws", 1) \
        + f"/v1/sessions/{session}/mesh/ws"
    if params:
        ws_url += "?" + "&".join(f"{k}={v}" for k, v in params.items())
    with connect(ws_url, additional_headers={"Authorization": f"Bearer {token}"},
                 max_size=None, open_timeout=timeout_s) as ws:
        for data in ws:
            yield decode(data)
