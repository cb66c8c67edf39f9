"""The FastAPI application: authentication, error mapping, health and metrics, the routers."""

from __future__ import annotations

import hmac
import time
from pathlib import Path

from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from .. import __version__
from ..realtime import is_realtime
from ..whole_files import is_disk_full
from . import (
    routes_calibration,
    routes_data,
    routes_devices,
    routes_mesh,
    routes_sessions,
    routes_telemetry,
)
from .config import TOKEN_FILE
from .docs_pages import add_docs_pages
from .errors import ApiError, Invalid, Unauthorized, from_disk_full, http_status
from .journal import Journal
from .metrics import LoopStats, registry
from .plane import ControlPlane
from .sources import SourceError
from .supervisor import Supervisor, worker_state
from .ui_pages import add_ui_pages
from .validation_hints import body_fields, explained, route_of

API_PREFIX = "/v1"
#: The API's routers under API_PREFIX, in the order they are mounted, and whether each needs
#: the token (the WebSocket routers check it themselves, from the query).
ROUTERS = (
    (routes_sessions.router, True),
    (routes_data.router, True),
    (routes_calibration.router, True),
    (routes_devices.router, True),
    (routes_mesh.router, True),
    (routes_mesh.ws_router, False),
    (routes_telemetry.router, True),
    (routes_telemetry.ws_router, False),
)
_bearer = HTTPBearer(auto_error=False, description="the token `burrforce serve` printed")


def token_whereabouts(config: object) -> str:
    """Where the REST token is to be found, for a message that asks for it."""
    if getattr(config, "token", None):
        return "the token this server was given (serve --token or BURRFORCE_TOKEN)"
    data_dir = getattr(config, "data_dir", None)
    if data_dir is None:
        return "the token `burrforce serve` printed"
    path = Path(data_dir).expanduser() / TOKEN_FILE
    return (f"the token is in {path} on the server's machine (`burrforce serve` shows it at "
            "its first start)")


def create_app(plane: ControlPlane, token: str, stats: LoopStats,
               supervisor: Supervisor | None = None, journal: Journal | None = None
               ) -> FastAPI:
    """The REST app over ``plane``. Every route except /v1/health needs ``token``;
    ``journal``: the session journal, whose state /v1/health and /metrics show."""
    where = token_whereabouts(plane.config)

    def authorize(credentials: HTTPAuthorizationCredentials | None = Depends(_bearer)) -> None:
        if credentials is None or not hmac.compare_digest(credentials.credentials.encode(),
                                                          token.encode()):
            raise Unauthorized(f"missing or wrong bearer token (Authorization: Bearer TOKEN): "
                               f"{where}")

    app = FastAPI(
        title="burrforce control plane", version=__version__,
        description="Sessions, bones, model parameters, exports and statistics of a burrforce "
                    "haptic force server. Forces stream over UDP (proto/SPEC.md); this API "
                    "configures what they are computed from. Units are in field names.",
        # FastAPI's own pages load their scripts from a CDN: add_docs_pages serves them.
        docs_url=None, redoc_url=None,
    )
    add_docs_pages(app)
    add_ui_pages(app)
    app.state.plane = plane
    app.state.stats = stats
    app.state.token = token
    # The browser origins besides the server's own that may open its WebSockets
    # (push_sockets.foreign_origin): those allowed to call the API.
    app.state.ws_origins = tuple(plane.config.cors_origins)
    # The telemetry routes read the loop's state from it (routes_telemetry.loop_state).
    app.state.supervisor = supervisor
    if plane.config.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(plane.config.cors_origins),
                           allow_methods=["*"], allow_headers=["Authorization",
                                                               "Content-Type"])

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        # The one place a domain error becomes HTTP (errors.HTTP_STATUS).
        headers = {"WWW-Authenticate": "Bearer"} if isinstance(exc, Unauthorized) else None
        # 422 keeps FastAPI's documented form (a list of errors) for every cause.
        detail = ([{"loc": [], "msg": exc.detail, "type": "value_error"}]
                  if isinstance(exc, Invalid) else exc.detail)
        return JSONResponse({"detail": detail}, status_code=http_status(exc), headers=headers)

    @app.exception_handler(SourceError)
    async def _source_error(request: Request, exc: SourceError) -> JSONResponse:
        # A bad bone source or snapshot name raised anywhere below a route: its own error.
        return await _api_error(request, exc.as_api_error())

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError) -> JSONResponse:
        # A full disk where no service said what it was writing: still an answer (507), not
        # a bare 500. Any other OSError is a bug, answered 500 with its traceback logged.
        if not is_disk_full(exc):
            raise exc
        return await _api_error(request, from_disk_full(exc, plane.storage.data_dir))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        fields = body_fields(route_of(request))
        json_body = "json" in request.headers.get("content-type", "")
        errors = [{"loc": list(e.get("loc", ())), "msg": explained(e, fields, json_body),
                   "type": e.get("type", "")} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    @app.get(API_PREFIX + "/health", tags=["system"])
    def health(response: Response) -> dict:
        """Liveness without a token: are all hot-loop workers running (503 if one is not,
        e.g. while it is restarted after a crash), how many sessions, the restarts; per
        worker (``workers``): pid, UDP endpoint, sessions, state, restarts. ``udp`` is worker
        0's endpoint; each session's own is in its view. ``journal``: ok, or degraded while a
        session's journal cannot be written (``status`` then says degraded, still 200: a
        restart would lose carving, not gain any), what resuming sessions at start lost, and
        the journals that could not be resumed and were kept aside."""
        loop = supervisor.public() if supervisor is not None else None
        workers = []
        for index, hot in enumerate(list(plane.workers)):
            up = hot.is_alive()
            workers.append({
                "index": index, "pid": hot.pid if up else None,
                "udp": {"host": hot.address[0], "port": hot.address[1]}
                if hot.address else None,
                "sessions": len(plane.worker_sessions(index)),
                "state": worker_state(supervisor, hot, index),
                "restarts": supervisor.worker_restarts(index) if supervisor is not None else 0,
                # SCHED_FIFO granted (``serve --realtime``), read from the scheduler itself.
                "realtime": up and is_realtime(hot.pid),
            })
        alive = all(w["state"] == "running" for w in workers)
        if not alive:
            response.status_code = 503
        latest = stats.latest
        status = "ok" if alive else (f"hot loop {loop['state']}" if loop else "hot loop down")
        if loop is not None and loop["state"] == "running" and not alive:
            status = "hot loop down"
        journaled = journal.public() if journal is not None else {"state": "off"}
        if alive and journaled["state"] == "degraded":
            status = "degraded"
        return {"status": status, "hot_loop": alive, "supervisor": loop,
                "journal": journaled,
                "version": __version__,
                "uptime_s": round(time.time() - plane.started_s, 1),
                "sessions": len(plane.sessions),
                "udp": workers[0]["udp"],
                "workers": workers,
                "packets_received": latest["counters"]["received"] if latest else None}

    reg = registry(stats, getattr(plane, "devices", None))
    if supervisor is not None:
        reg.register(supervisor)
    if journal is not None:
        reg.register(journal)

    @app.get("/metrics", tags=["system"], dependencies=[Depends(authorize)],
             response_class=Response)
    def metrics() -> Response:
        """Prometheus text format: packets by outcome, the tick-time histogram, per-session
        counters, bone versions, removed volume."""
        return Response(generate_latest(reg), media_type=CONTENT_TYPE_LATEST)

    for router, needs_token in ROUTERS:
        app.include_router(router, prefix=API_PREFIX,
                           dependencies=[Depends(authorize)] if needs_token else None)
    return app
