"""Sessions: create, list, inspect, delete, reset; parameters, features, materials, state."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Path, Query, Request, Response

from ..bone import Material
from .deps import PlaneDep, SessionPath, wait_for
from .errors import Gone, Invalid, Unavailable
from .models import (
    BoneRequest,
    Features,
    JobView,
    MaterialBody,
    MaterialPatch,
    MaterialView,
    Parameters,
    ParametersView,
    SessionCreate,
    SessionCreated,
    SessionView,
)
from .plane import ControlPlane
from .sessions import ManagedSession
from .views import parameters_view, session_view

router = APIRouter(tags=["sessions"])
def view(plane: ControlPlane, s: ManagedSession, key: bool = False) -> dict:
    """``s`` as the session routes answer with it (``views.session_view``)."""
    return session_view(s, plane.address(s), plane.devices.attached(s.id), key)


@router.post("/sessions", status_code=201, response_model=SessionCreated)
def create_session(body: SessionCreate, plane: PlaneDep, response: Response,
                   wait: bool = Query(True, description="answer when the bone is loaded "
                                                        "(false: at once, 202, poll the job)")
                   ) -> dict:
    """Create a session on a bone. The answer holds its id, key (shown only here) and UDP
    endpoint. With ``wait=false`` it answers 202 at once; ``GET /v1/jobs/{job}`` follows the
    load."""
    b = body.bone
    source = plane.resolve(b.source, b.kind, b.voxel_mm, b.spacing_mm)
    session, job = plane.create_session(body.id, source, body.parameters, body.features,
                                        body.authenticated)
    wait_for(plane, job.id, wait)
    if session.state == "failed":
        plane.delete_session(session.id)
        if job.failure is Unavailable:  # the server's trouble (a hot-loop restart)
            raise Unavailable(f"the session could not be started, try again: "
                              f"{session.error}")
        if job.failure is not None and job.failure is not Gone:  # the loop refused it
            raise job.failure(f"the session could not be started: {session.error}")
        raise Invalid(f"the bone could not be loaded: {session.error}")
    if session.state != "ready":
        response.status_code = 202
    response.headers["Location"] = f"/v1/sessions/{session.id}"
    return view(plane, session, key=True)


@router.get("/sessions", response_model=list[SessionView])
def list_sessions(plane: PlaneDep) -> list[dict]:
    return [view(plane, s) for s in sorted(plane.sessions.values(),
                                                   key=lambda s: s.id)]


@router.get("/sessions/{session_id}", response_model=SessionView)
def get_session(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    return view(plane, plane.get(session_id))


@router.delete("/sessions/{session_id}", status_code=204)
def delete_session(plane: PlaneDep, session_id: int = SessionPath) -> Response:
    """Remove the session: its datagrams get UNKNOWN_SESSION notices (a client zeroes its
    force), its bone is freed, a recording is closed."""
    plane.delete_session(session_id)
    return Response(status_code=204)


@router.post("/sessions/{session_id}/reset", status_code=202, response_model=JobView)
def reset_session(plane: PlaneDep, session_id: int = SessionPath,
                  wait: bool = Query(True)) -> dict:
    """Reload the bone from its source (uncarved; Us/K set over REST are kept) and start a
    new stream."""
    job = plane.reset(session_id)
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


@router.post("/sessions/{session_id}/restart-stream", status_code=204)
def restart_stream(plane: PlaneDep, session_id: int = SessionPath) -> Response:
    """End the session's stream: its next POSE is answered WRONG_STREAM, and the client says
    hello for a new one (SPEC 5.2). A v2 client never needs it to recover; it is for an
    operator who wants a stream cut off."""
    plane.restart_stream(session_id)
    return Response(status_code=204)


@router.put("/sessions/{session_id}/bone", status_code=202, response_model=JobView)
def load_bone(body: BoneRequest, plane: PlaneDep, session_id: int = SessionPath,
              wait: bool = Query(True)) -> dict:
    """Load another bone into the session (the stream continues on the new bone)."""
    source = plane.resolve(body.source, body.kind, body.voxel_mm, body.spacing_mm)
    job = plane.load_bone(session_id, source)
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


@router.get("/sessions/{session_id}/parameters", response_model=ParametersView)
def get_parameters(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    return parameters_view(plane.get(session_id))


@router.patch("/sessions/{session_id}/parameters", response_model=ParametersView)
def patch_parameters(body: Parameters, plane: PlaneDep,
                     session_id: int = SessionPath) -> dict:
    """Change any subset. ``us_n_mm2`` and ``k`` set the primary material's (see
    ``primary_material``; /materials sets the others). Applied between two packets; a frame
    or burr change restarts the velocity estimate."""
    return parameters_view(plane.update_parameters(session_id, body))


@router.get("/sessions/{session_id}/features")
def get_features(plane: PlaneDep, session_id: int = SessionPath) -> Features:
    return plane.get(session_id).features


@router.put("/sessions/{session_id}/features")
def put_features(body: Features, plane: PlaneDep, session_id: int = SessionPath) -> Features:
    """What the scene uses; off is skipped in the hot loop."""
    return plane.update_features(session_id, body).features


@router.get("/sessions/{session_id}/materials", response_model=list[MaterialView])
def get_materials(plane: PlaneDep, session_id: int = SessionPath) -> list[dict]:
    """The material table: label → name, Us, K, forbidden."""
    s = plane.ready(session_id)
    return [{"label": label, **asdict(m)} for label, m in s.materials]


@router.put("/sessions/{session_id}/materials/{label}", response_model=MaterialView)
def put_material(body: MaterialBody, plane: PlaneDep, session_id: int = SessionPath,
                 label: int = Path(ge=1, le=255)) -> dict:
    try:
        material = Material(**body.model_dump())
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    s = plane.set_material(session_id, label, material)
    return {"label": label, **asdict(s.materials[label])}


@router.patch("/sessions/{session_id}/materials/{label}", response_model=MaterialView)
def patch_material(body: MaterialPatch, plane: PlaneDep, session_id: int = SessionPath,
                   label: int = Path(ge=1, le=255)) -> dict:
    changes = body.model_dump(exclude_none=True)
    s = plane.set_material(session_id, label, None, changes)
    return {"label": label, **asdict(s.materials[label])}


@router.get("/sessions/{session_id}/state")
def get_state(request: Request, plane: PlaneDep, session_id: int = SessionPath,
              max_events: int = Query(100, ge=0, le=10_000)) -> dict:
    """Bone version, removed volume per material, forbidden-contact events (the latest
    ``max_events``), counters, tick-time quantiles and the haptic output (coupling stiffness
    and damping in use, the passivity observer's energy, the proxy) and how its journal
    stands (``journal``: as in the session's view)."""
    state = plane.session_state(session_id, max_events)
    state["journal"] = plane.get(session_id).journal.view()
    latest = request.app.state.stats.latest
    if latest and session_id in latest["sessions"]:
        s = latest["sessions"][session_id]
        state["tick_p50_us"], state["tick_p99_us"] = s["tick_p50_us"], s["tick_p99_us"]
    return state
