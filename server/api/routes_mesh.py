"""The carved bone as mesh chunks (``proto/MESH.md``): a REST page and a WebSocket that pushes
every change."""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from typing import Literal

from fastapi import APIRouter, Query, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from ...proto.mesh_chunks import FORMAT_VERSION, MEDIA_TYPE, encode
from ..bone.chunks import CHUNK_BRICKS_DEFAULT, CHUNK_BRICKS_MAX
from .deps import PlaneDep, SessionPath, get_plane
from .errors import ApiError, Conflict
from .generation import bone_generation
from .mesh_pages import (
    MAX_BYTES_DEFAULT,
    MAX_BYTES_MAX,
    MAX_BYTES_MIN,
    MeshRequest,
    mesh_page,
)
from .models import MAX_BONE_VERSION
from .plane import ControlPlane
from .push_sockets import (
    accept,
    admitted_session_id,
    close_reason,
    query_int,
    release_socket_slot,
    take_socket_slot,
    watch_disconnect,
)
from .sessions import ManagedSession

router = APIRouter(tags=["exports"])
#: Authenticates itself: a WebSocket client may not be able to set a header.
ws_router = APIRouter()

Frame = Literal["session", "server"]
Winding = Literal["ccw", "cw"]
ChunkBricks = Query(CHUNK_BRICKS_DEFAULT, ge=1, le=CHUNK_BRICKS_MAX,
                    description="chunk edge in 8-voxel bricks")
FrameQuery = Query("session", description="session: the session's engine frame and unit; "
                                          "server: the server frame, mm")
WindingQuery = Query("ccw", description="ccw: the right-handed cross product of a triangle's "
                                        "edges points out of the bone; cw: into it")
GenerationQuery = Query(None, ge=0, le=(1 << 63) - 1,
                        description="the bone generation your chunks are of (version 2 "
                                    "messages carry it); another one than the bone's: every "
                                    "chunk, FULL")
FormatQuery = Query(1, ge=1, le=FORMAT_VERSION,
                    description="the message format: 1, or 2 (with the bone generation)")


def _request(session: ManagedSession, chunk_bricks: int, frame: str,
             winding: str) -> MeshRequest:
    c = session.config
    return MeshRequest(session.id, chunk_bricks, frame == "session", winding == "cw",
                       c.frame, tuple(c.placement_position), tuple(c.placement_orientation))


def _meshable(plane: ControlPlane, session_id: int) -> ManagedSession:
    session = plane.ready(session_id)
    if not session.features.deltas:
        raise Conflict("the session has deltas off (features.deltas): no mesh updates")
    return session


@router.get("/sessions/{session_id}/mesh", response_class=Response,
            responses={200: {"content": {MEDIA_TYPE: {}}}})
def mesh(plane: PlaneDep, session_id: int = SessionPath,
         since: int | None = Query(None, ge=0, le=MAX_BONE_VERSION,
                                   description="the bone version your chunks "
                                                           "are at; omitted: every chunk"),
         chunk_bricks: int = ChunkBricks, frame: Frame = FrameQuery,
         winding: Winding = WindingQuery,
         generation: int | None = GenerationQuery,
         format_version: int = FormatQuery,
         cursor: int = Query(0, ge=0, le=(1 << 32) - 1,
                             description="the previous page's next_cursor"),
         max_bytes: int = Query(MAX_BYTES_DEFAULT, ge=MAX_BYTES_MIN, le=MAX_BYTES_MAX,
                                description="a page's size budget, bytes")) -> Response:
    """The carved bone's surface as chunk meshes changed since bone version ``since`` (one
    page: follow ``next_cursor`` while the MORE flag is set, with the same query). Binary,
    little-endian: the format is in proto/MESH.md. Chunks of another bone ``generation``
    (the bone was reset, reloaded or restored) are all replaced: a FULL answer. The WebSocket
    ``/v1/sessions/{id}/mesh/ws`` (same query, plus ``interval_ms``; the token also as
    ``?token=``) pushes the same messages as the bone changes."""
    session = _meshable(plane, session_id)
    req = _request(session, chunk_bricks, frame, winding)
    current = bone_generation(session)  # before the reader: generation.py
    if generation is not None and generation != current:
        since = None
    stamp = current if format_version >= 2 else None
    page = session.read_bone(lambda g: mesh_page(g, req, since, cursor, max_bytes, stamp))
    return Response(encode(page), media_type=MEDIA_TYPE)


@dataclass(frozen=True)
class WsQuery:
    """The WebSocket's query, checked by hand: FastAPI would refuse a bad one with a bare
    HTTP 403 before the handshake, telling the client nothing."""

    since: int | None
    chunk_bricks: int
    frame: str
    winding: str
    interval_ms: int
    token: str | None
    generation: int | None = None
    format_version: int = 1

    @classmethod
    def parse(cls, q) -> WsQuery:
        def integer(name: str, default: int | None, lo: int, hi: int) -> int | None:
            return query_int(q.get(name), name, default, lo, hi)

        def choice(name: str, default: str, options: tuple[str, ...]) -> str:
            value = q.get(name, default)
            if value not in options:
                raise ValueError(f"{name} must be one of {', '.join(options)}, got {value!r}")
            return value

        return cls(integer("since", None, 0, (1 << 63) - 1),
                   integer("chunk_bricks", CHUNK_BRICKS_DEFAULT, 1, CHUNK_BRICKS_MAX),
                   choice("frame", "session", ("session", "server")),
                   choice("winding", "ccw", ("ccw", "cw")),
                   integer("interval_ms", 33, 10, 1000), q.get("token"),
                   integer("generation", None, 0, (1 << 63) - 1),
                   integer("format_version", 1, 1, FORMAT_VERSION))


#: Mesh WebSockets open at once, server-wide: each meshes the bone on the control plane's
#: threads; one more is closed with 4503.
MAX_MESH_SOCKETS = 32


@ws_router.websocket("/sessions/{session_id}/mesh/ws")
async def mesh_ws(ws: WebSocket, session_id: str) -> None:
    """Pushes mesh-chunk messages (proto/MESH.md): everything changed since ``since`` at
    once (everything, FULL, when ``generation`` is not the bone's), then each change, at most
    every ``interval_ms``, and everything again when the bone is replaced. Query: since,
    generation, format_version, chunk_bricks, frame, winding, interval_ms, token (or the
    Authorization header)."""
    # Accepted first: a close before the handshake reaches the client as a bare HTTP 403,
    # without the code and reason that say what was wrong.
    await accept(ws)
    try:
        query = WsQuery.parse(ws.query_params)
    except ValueError as exc:
        await ws.close(4422, close_reason(str(exc)))
        return
    sid = await admitted_session_id(ws, session_id, query.token)
    if sid is None:
        return
    plane = get_plane(ws)
    try:
        session = _meshable(plane, sid)
    except ApiError as exc:
        await ws.close(4000 + exc.status, close_reason(exc.detail))
        return
    since, chunk_bricks, frame, winding = (query.since, query.chunk_bricks, query.frame,
                                           query.winding)
    interval_ms = query.interval_ms
    req = _request(session, chunk_bricks, frame, winding)
    generation = bone_generation(session)  # before the reader: generation.py
    reader = session.reader
    if query.generation is not None and query.generation != generation:
        since = None
    sent_for: int | None = None  # the bone version the client was last brought up to
    loop = asyncio.get_running_loop()
    if not await take_socket_slot(ws, "mesh", MAX_MESH_SOCKETS):
        return
    gone, watcher = watch_disconnect(ws)
    try:
        while not gone.is_set():
            started = loop.time()
            current = plane.sessions.get(session.id)
            if current is None or current.state != "ready":
                await ws.close(1001, f"session {session.id} is gone")
                return
            fresh = _request(current, chunk_bricks, frame, winding)
            now_generation = bone_generation(current)  # before the reader: generation.py
            if current.reader is not reader or fresh != req or now_generation != generation:
                # A new bone, or a new frame or placement (every coordinate moves): start
                # over with every chunk.
                reader, req, since, sent_for = current.reader, fresh, None, None
                generation = now_generation
            stamp = generation if query.format_version >= 2 else None
            version = await run_in_threadpool(reader.read_published, lambda g: int(g.version))
            if version != sent_for:
                low, cursor = None, 0
                while True:
                    page = await run_in_threadpool(
                        reader.read_published,
                        lambda g, r=req, n=since, c=cursor, s=stamp: mesh_page(
                            g, r, n, c, MAX_BYTES_DEFAULT, s))
                    await ws.send_bytes(encode(page))
                    low = page.bone_version if low is None else min(low, page.bone_version)
                    if not page.more:
                        break
                    cursor = page.next_cursor
                since = sent_for = low
            # At most one update per interval, counted from the last one's start: meshing
            # and sending take part of it.
            rest = interval_ms / 1000.0 - (loop.time() - started)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(gone.wait(), max(rest, 0.001))
    except (WebSocketDisconnect, RuntimeError):
        return  # the client left mid-send
    except ValueError as exc:  # a session setting the mesh cannot be made in
        with contextlib.suppress(RuntimeError):
            await ws.close(4422, close_reason(str(exc)))
    except TimeoutError:  # the loop held a carving tick open: tell the client, let it retry
        with contextlib.suppress(RuntimeError):
            await ws.close(1013, "the bone was busy; reconnect")
    finally:
        watcher.cancel()
        release_socket_slot(ws, "mesh")
