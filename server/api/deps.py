"""What the routes share: the control plane as one FastAPI dependency (``PlaneDep``), the
session id in a path, and waiting for a bone load."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path
from starlette.requests import HTTPConnection

from .plane import ControlPlane


def get_plane(connection: HTTPConnection) -> ControlPlane:
    """The app's control plane (``create_app`` sets it), for a request or a WebSocket."""
    return connection.app.state.plane


#: A route's parameter ``plane: PlaneDep`` receives the control plane.
PlaneDep = Annotated[ControlPlane, Depends(get_plane)]
#: A session id in a route's path (uint32).
SessionPath = Path(ge=0, le=(1 << 32) - 1, description="session id")
#: How long ``?wait=true`` waits for a bone to load, s.
WAIT_LIMIT_S = 600.0


def wait_for(plane: ControlPlane, job_id: str, wait: bool) -> None:
    """With ``wait``, until job ``job_id`` is done or failed (at most ``WAIT_LIMIT_S``)."""
    if wait:
        plane.wait(plane.jobs[job_id], WAIT_LIMIT_S)
