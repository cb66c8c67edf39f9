"""A session's live telemetry: the latest packet over REST, a stream of them over a WebSocket,
and the session's report from its sampled history.

All read the hot loop's state from shared memory (``api.telemetry``, ``api.history``): none
calls into the loop per sample, so a browser plotting at 60 Hz costs the packet path nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Literal

from fastapi import APIRouter, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import Response

from ..report import SessionReport, report_from_live
from . import push_sockets
from .deps import PlaneDep, SessionPath, get_plane
from .errors import ApiError, Unavailable
from .plane import ControlPlane
from .report_http import REPORT_RESPONSES, ReportFormat, ReportThreshold, report_response
from .sessions import ManagedSession
from .supervisor import worker_state
from .telemetry import TelemetrySample

#: The REST route: the app adds its bearer check, as for every router.
router = APIRouter()
#: The WebSocket: checks the token itself (header, subprotocol or ``?token=``), as the mesh's.
ws_router = APIRouter()

HZ_MIN = 10
HZ_MAX = 60
HZ_DEFAULT = 30
#: An unchanged sample is sent again after this long, s (the client sees the stream alive).
KEEPALIVE_S = 1.0
#: Telemetry WebSockets open at once, server-wide (each wakes up to 60 times a second on the
#: event loop every route shares); one more is closed with 4503.
MAX_TELEMETRY_SOCKETS = 32
#: Forbidden-contact events a live report asks the loop for: all the engine keeps.
REPORT_MAX_EVENTS = 10_000


def loop_state(request: Request | WebSocket, session: ManagedSession) -> str:
    """The state of the hot loop serving ``session``, as /v1/health reports it
    (``supervisor.worker_state``; ``app.state.supervisor``)."""
    index = session.worker
    return worker_state(getattr(request.app.state, "supervisor", None),
                        get_plane(request).workers[index], index)


def _sample(request: Request | WebSocket, plane: ControlPlane,
            session_id: int) -> TelemetrySample:
    session = plane.ready(session_id)
    _require_telemetry(plane)
    sample = plane.telemetry.sample(session_id, loop=loop_state(request, session))
    if sample is None:
        raise Unavailable(f"session {session_id} has no telemetry yet (its hot loop is "
                          "starting); try again")
    return sample


def _require_telemetry(plane: ControlPlane) -> None:
    if not plane.telemetry.available:
        raise Unavailable("no live telemetry on this server: it needs room in /dev/shm "
                          "(the shared bones fell back to a disk folder; in docker, raise "
                          "shm_size)")


@router.get("/sessions/{session_id}/telemetry", tags=["sessions"])
def telemetry(request: Request, plane: PlaneDep, session_id: int = SessionPath) -> dict:
    """The session's latest packet as the hot loop keeps it: pose (server frame, mm), the
    reply's force, components, vibration, status and bone version, the server's residence
    time (t_send − t_recv, µs: the client measures its own round trip from the echoed
    t_client_us), the model stage's tick times, ``age_s`` (how long ago the packet came:
    it grows while nothing streams, or while the hot loop restarts) and ``loop`` (the
    supervisor's state of the session's hot loop: running, restarting, lost, down). Read
    from shared memory, not from the loop. The WebSocket
    ``/v1/sessions/{id}/telemetry/ws?hz=30`` pushes the same."""
    return _sample(request, plane, session_id).to_dict()


def live_report(plane: ControlPlane, session_id: int, threshold_N: float) -> SessionReport:
    """``session_id``'s report: its telemetry history (``plane.history``) with its engine's
    removed volume and forbidden contacts (the loop's ``session_state``)."""
    session = plane.ready(session_id)
    _require_telemetry(plane)
    state = plane.session_state(session_id, REPORT_MAX_EVENTS)
    # The history after the state: its last sample is then no older than the state's events.
    h = plane.history.view(session_id)
    return report_from_live(
        session_id, h.t_s, h.status, h.hand_force_N, state.get("removed_mm3") or {},
        state.get("events") or [], threshold_N, hz=h.hz, installs=h.installs,
        dropped=h.dropped, wall_offset_s=h.wall_offset_s, more_notes=session.journal.notes())


@router.get("/sessions/{session_id}/report", tags=["sessions"], responses=REPORT_RESPONSES)
def session_report(plane: PlaneDep, session_id: int = SessionPath,
                   format: Literal["json", "html"] = ReportFormat,
                   threshold_n: float = ReportThreshold) -> Response:
    """The live session's report, as a recording's (``GET /v1/recordings/NAME/report``):
    duration, time cutting, bone removed per material, forbidden contacts (time, structure,
    position), the hand force (peak, mean in contact, time above ``threshold_n``) and its
    plot. Times are from the first sample the server kept of the session (or from a
    forbidden contact in the packets just before it).

    Resolution: the hand force and the cutting time are sampled at 100 Hz from the live
    telemetry (``api.history``), not taken from every packet: a 1 kHz stream's ticks between
    samples are not seen (a peak shorter than 10 ms may be missed). The history keeps the
    last 2 h. The removed volume per material and the forbidden contacts are the session
    engine's own, exact, counted since the bone was loaded (kept across restarts of the hot
    loop and of ``serve``; a resume from a damaged journal says what it lost). The
    report's ``notes`` say all of this. 404: no such session; 409: not ready; 422: a bad
    threshold; 503: no live telemetry on this server."""
    report = live_report(plane, session_id, threshold_n)
    return report_response(report, format)


@ws_router.websocket("/sessions/{session_id}/telemetry/ws")
async def telemetry_ws(ws: WebSocket, session_id: str) -> None:
    """Pushes the session's telemetry (JSON, as ``GET …/telemetry``) ``hz`` times a second
    (10–60, default 30) when it changed, and at least once a second. Query: hz, token (or
    the Authorization header, or the subprotocol ``bearer.TOKEN``). Closes with 4422 (bad
    query), 4401 (token), 4404 / 4409 (no such session / not ready), 4503
    (``MAX_TELEMETRY_SOCKETS`` are open, or no live telemetry on this server), 1001 (the
    session was deleted)."""
    # Accepted first: a close before the handshake reaches the client as a bare HTTP 403.
    await push_sockets.accept(ws)
    try:
        hz = push_sockets.query_int(ws.query_params.get("hz"), "hz", HZ_DEFAULT, HZ_MIN, HZ_MAX)
    except ValueError as exc:
        await ws.close(4422, push_sockets.close_reason(str(exc)))
        return
    sid = await push_sockets.admitted_session_id(ws, session_id, ws.query_params.get("token"))
    if sid is None:
        return
    plane = get_plane(ws)
    try:
        session = plane.ready(sid)
        _require_telemetry(plane)
    except ApiError as exc:
        await ws.close(4000 + exc.status, push_sockets.close_reason(exc.detail))
        return
    if not await push_sockets.take_socket_slot(ws, "telemetry", MAX_TELEMETRY_SOCKETS):
        return
    try:
        await _push(ws, plane, session, sid, hz)
    finally:
        push_sockets.release_socket_slot(ws, "telemetry")


async def _push(ws: WebSocket, plane: ControlPlane, session: ManagedSession, sid: int,
                hz: int) -> None:
    gone, watcher = push_sockets.watch_disconnect(ws)
    loop = asyncio.get_running_loop()
    period = 1.0 / hz
    last_key = None
    last_sent = -KEEPALIVE_S
    try:
        while not gone.is_set():
            started = loop.time()
            if plane.sessions.get(sid) is not session:  # deleted (its id may be reused)
                await ws.close(1001, f"session {sid} is gone")
                return
            # Tens of µs of copying from shared memory: no thread hop needed.
            sample = plane.telemetry.sample(sid, loop=loop_state(ws, session))
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
