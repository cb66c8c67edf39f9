"""A session's live telemetry: the latest packet over REST, a stream of them over a WebSocket.

Both read the hot loop's state from shared memory (``api.telemetry``): neither calls into the
loop, so a browser plotting at 60 Hz costs the packet path nothing.
"""

from __future__ import annotations

import asyncio
import contextlib

from fastapi import APIRouter, Request, WebSocket, WebSocketDisconnect

from .manager import ApiError, ControlPlane
from .routes_mesh import _authorized, _reason, watch_disconnect
from .routes_sessions import SessionPath
from .telemetry import TelemetrySample

#: The REST route: the app adds its bearer check, as for every router.
router = APIRouter()
#: The WebSocket: checks the token itself (header or ``?token=``), as the mesh's does.
ws_router = APIRouter()

HZ_MIN = 10
HZ_MAX = 60
HZ_DEFAULT = 30
#: An unchanged sample is sent again after this long, s (the client sees the stream alive).
KEEPALIVE_S = 1.0


def _plane(request: Request | WebSocket) -> ControlPlane:
    return request.app.state.plane


def _sample(plane: ControlPlane, session_id: int) -> TelemetrySample:
    plane.ready(session_id)
    if not plane.telemetry.available:
        raise ApiError(503, "no live telemetry on this server: it needs room in /dev/shm "
                            "(the shared bones fell back to a disk folder; in docker, raise "
                            "shm_size)")
    sample = plane.telemetry.sample(session_id)
    if sample is None:
        raise ApiError(503, f"session {session_id} has no telemetry yet (its hot loop is "
                            "starting); try again")
    return sample


@router.get("/sessions/{session_id}/telemetry", tags=["sessions"])
def telemetry(request: Request, session_id: int = SessionPath) -> dict:
    """The session's latest packet as the hot loop keeps it: pose (server frame, mm), the
    reply's force, components, vibration, status and bone version, the server's residence
    time (t_send − t_recv, µs: the client measures its own round trip from the echoed
    t_client_us), the model stage's tick times. Read from shared memory, not from the loop.
    The WebSocket ``/v1/sessions/{id}/telemetry/ws?token=…&hz=30`` pushes the same."""
    return _sample(_plane(request), session_id).to_dict()


def _hz(text: str | None) -> int:
    if text is None:
        return HZ_DEFAULT
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"hz must be an integer, got {text!r}") from None
    if not HZ_MIN <= value <= HZ_MAX:
        raise ValueError(f"hz must be in {HZ_MIN}..{HZ_MAX}, got {value}")
    return value


@ws_router.websocket("/sessions/{session_id}/telemetry/ws")
async def telemetry_ws(ws: WebSocket, session_id: str) -> None:
    """Pushes the session's telemetry (JSON, as ``GET …/telemetry``) ``hz`` times a second
    (10–60, default 30) when it changed, and at least once a second. Query: hz, token (or
    the Authorization header). Closes with 4422 (bad query), 4401 (token), 4404 / 4409 (no
    such session / not ready), 1001 (the session was deleted)."""
    # Accepted first: a close before the handshake reaches the client as a bare HTTP 403.
    await ws.accept()
    try:
        hz = _hz(ws.query_params.get("hz"))
    except ValueError as exc:
        await ws.close(4422, _reason(str(exc)))
        return
    if not _authorized(ws, ws.query_params.get("token")):
        await ws.close(4401, "missing or wrong bearer token (Authorization: Bearer TOKEN, "
                             "or ?token=TOKEN)")
        return
    if not (session_id.isascii() and session_id.isdecimal()) or int(session_id) >= 1 << 32:
        await ws.close(4422, _reason(f"session id must be an integer in 0..2^32-1, got "
                                     f"{session_id!r}"))
        return
    plane = _plane(ws)
    sid = int(session_id)
    try:
        plane.ready(sid)
        if not plane.telemetry.available:
            raise ApiError(503, "no live telemetry on this server: it needs room in /dev/shm")
    except ApiError as exc:
        await ws.close(4000 + exc.status, _reason(exc.detail))
        return
    gone, watcher = watch_disconnect(ws)
    loop = asyncio.get_running_loop()
    period = 1.0 / hz
    last_key = None
    last_sent = -KEEPALIVE_S
    try:
        while not gone.is_set():
            started = loop.time()
            if sid not in plane.sessions:
                await ws.close(1001, f"session {sid} is gone")
                return
            # Tens of µs of copying from shared memory: no thread hop needed.
            sample = plane.telemetry.sample(sid)
            if sample is not None and (sample.key != last_key
                                       or started - last_sent >= KEEPALIVE_S):
                await ws.send_json(sample.to_dict())
                last_key, last_sent = sample.key, started
            rest = period - (loop.time() - started)
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(gone.wait(), max(rest, 0.001))
    except (WebSocketDisconnect, RuntimeError):
        return
    finally:
        watcher.cancel()
