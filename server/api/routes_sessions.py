"""Sessions: create, list, inspect, delete, reset; parameters, features, materials, state."""

from __future__ import annotations

from dataclasses import asdict

from fastapi import APIRouter, Path, Query, Request, Response

from ..bone import Material
from ..model.shapes import profile_points
from .manager import ApiError, ControlPlane, ManagedSession
from .models import (
    BoneRequest,
    Features,
    MaterialBody,
    MaterialPatch,
    Parameters,
    SessionCreate,
)

router = APIRouter(tags=["sessions"])
SessionPath = Path(ge=0, le=(1 << 32) - 1, description="session id")
#: How long ``?wait=true`` waits for a bone to load, s.
WAIT_LIMIT_S = 600.0


def wait_for(plane: ControlPlane, job_id: str, wait: bool) -> None:
    if wait:
        plane.wait(plane.jobs[job_id], WAIT_LIMIT_S)


def _plane(request: Request) -> ControlPlane:
    return request.app.state.plane


def session_view(plane: ControlPlane, s: ManagedSession, key: bool = False) -> dict:
    host, port = plane.address(s) or ("", 0)
    view = {
        "id": s.id,
        "state": s.state,
        "error": s.error,
        "job": s.job_id,
        "udp": {"host": host, "port": port},
        "worker": s.worker,
        "authenticated": s.key_hex is not None,
        "source": s.source.source,
        "bone": s.bone_info,
        "frame": s.config.frame,
        "features": s.features.model_dump(),
        "output": s.output,
        # The haptic device the force is coupled for, and whether a local device loop
        # (PUT …/device) drives this session.
        "device": None if s.device is None else s.device.name,
        "device_attached": plane.devices.attached(s.id),
        "recording": s.recording["name"] if s.recording else None,
        "created": s.created_s,
    }
    if key:
        view["key"] = s.key_hex
    return view


def parameters_view(s: ManagedSession) -> dict:
    primary = s.primary_label
    material = s.materials[primary] if s.materials is not None and primary is not None \
        else None
    pending = s.overrides.get(None, {})
    return {
        "us_n_mm2": material.us_n_mm2 if material else pending.get("us_n_mm2"),
        "k": material.k if material else pending.get("k"),
        "primary_material": primary,
        "primary_material_name": material.name if material else None,
        "fd_N": s.vibration.fd_N, "g": s.vibration.g, "harmonic": s.vibration.harmonic,
        "burr": s.params.shape.to_dict(),
        "burr_calibrated": s.params.shape.cutter.calibrated,
        # For drawing the burr: its generatrix, tip to top, as (ρ, z) mm in the tool frame
        # (z along the axis toward the handle, origin at the burr's reference centre).
        "burr_profile_mm": profile_points(s.params.shape.shape.profile()).round(4).tolist(),
        "radius_mm": s.params.radius_mm, "spin": s.params.spin,
        "min_cutting_rpm": s.params.min_cutting_rpm,
        "shaft_radius_mm": s.shaft.radius_mm, "shaft_length_mm": s.shaft.length_mm,
        "shaft_stiffness_n_mm3": s.shaft.stiffness_n_mm3,
        "frame": s.config.frame,
        "tool_axis": list(s.config.tool_axis) if s.config.tool_axis else None,
        "placement_position": list(s.config.placement_position),
        "placement_orientation": list(s.config.placement_orientation),
        "device": None if s.device is None else s.device.name,
        "device_limits": None if s.device is None else {
            k: v for k, v in s.device.as_dict().items()
            if k != "name" and not k.startswith("sim_")},
    }


@router.post("/sessions", status_code=201)
def create_session(body: SessionCreate, request: Request, response: Response,
                   wait: bool = Query(True, description="answer when the bone is loaded "
                                                        "(false: at once, 202, poll the job)")
                   ) -> dict:
    """Create a session on a bone. The answer holds its id, key (shown only here) and UDP
    endpoint. With ``wait=false`` it answers 202 at once; ``GET /v1/jobs/{job}`` follows the
    load."""
    plane = _plane(request)
    b = body.bone
    source = plane.resolve(b.source, b.kind, b.voxel_mm, b.spacing_mm)
    session, job = plane.create_session(body.id, source, body.parameters, body.features,
                                        body.authenticated)
    wait_for(plane, job.id, wait)
    if session.state == "failed":
        plane.delete_session(session.id)
        if job.status == 503:  # the server's trouble (a hot-loop restart), not the bone's
            raise ApiError(503, f"the session could not be started, try again: "
                                f"{session.error}")
        raise ApiError(422, f"the bone could not be loaded: {session.error}")
    if session.state != "ready":
        response.status_code = 202
    response.headers["Location"] = f"/v1/sessions/{session.id}"
    return session_view(plane, session, key=True)


@router.get("/sessions")
def list_sessions(request: Request) -> list[dict]:
    plane = _plane(request)
    return [session_view(plane, s) for s in sorted(plane.sessions.values(),
                                                   key=lambda s: s.id)]


@router.get("/sessions/{session_id}")
def get_session(request: Request, session_id: int = SessionPath) -> dict:
    plane = _plane(request)
    return session_view(plane, plane.get(session_id))


@router.delete("/sessions/{session_id}", status_code=204)
def delete_session(request: Request, session_id: int = SessionPath) -> Response:
    """Remove the session: its datagrams get UNKNOWN_SESSION notices (a client zeroes its
    force), its bone is freed, a recording is closed."""
    _plane(request).delete_session(session_id)
    return Response(status_code=204)


@router.post("/sessions/{session_id}/reset", status_code=202)
def reset_session(request: Request, session_id: int = SessionPath,
                  wait: bool = Query(True)) -> dict:
    """Reload the bone from its source (uncarved; Us/K set over REST are kept) and start a
    new stream."""
    plane = _plane(request)
    job = plane.reset(session_id)
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


@router.post("/sessions/{session_id}/restart-stream", status_code=204)
def restart_stream(request: Request, session_id: int = SessionPath) -> Response:
    """End the session's stream: its next POSE is answered WRONG_STREAM, and the client says
    hello for a new one (SPEC 5.2). A v2 client never needs it to recover; it is for an
    operator who wants a stream cut off."""
    _plane(request).restart_stream(session_id)
    return Response(status_code=204)


@router.put("/sessions/{session_id}/bone", status_code=202)
def load_bone(body: BoneRequest, request: Request, session_id: int = SessionPath,
              wait: bool = Query(True)) -> dict:
    """Load another bone into the session (the stream continues on the new bone)."""
    plane = _plane(request)
    source = plane.resolve(body.source, body.kind, body.voxel_mm, body.spacing_mm)
    job = plane.load_bone(session_id, source)
    wait_for(plane, job.id, wait)
    return plane.jobs[job.id].public()


@router.get("/sessions/{session_id}/parameters")
def get_parameters(request: Request, session_id: int = SessionPath) -> dict:
    return parameters_view(_plane(request).get(session_id))


@router.patch("/sessions/{session_id}/parameters")
def patch_parameters(body: Parameters, request: Request,
                     session_id: int = SessionPath) -> dict:
    """Change any subset. ``us_n_mm2`` and ``k`` set the primary material's (see
    ``primary_material``; /materials sets the others). Applied between two packets; a frame
    or burr change restarts the velocity estimate."""
    plane = _plane(request)
    return parameters_view(plane.update_parameters(session_id, body))


@router.get("/sessions/{session_id}/features")
def get_features(request: Request, session_id: int = SessionPath) -> Features:
    return _plane(request).get(session_id).features


@router.put("/sessions/{session_id}/features")
def put_features(body: Features, request: Request, session_id: int = SessionPath) -> Features:
    """What the scene uses; off is skipped in the hot loop."""
    return _plane(request).update_features(session_id, body).features


@router.get("/sessions/{session_id}/materials")
def get_materials(request: Request, session_id: int = SessionPath) -> list[dict]:
    """The material table: label → name, Us, K, forbidden."""
    s = _plane(request).ready(session_id)
    return [{"label": label, **asdict(m)} for label, m in s.materials]


@router.put("/sessions/{session_id}/materials/{label}")
def put_material(body: MaterialBody, request: Request, session_id: int = SessionPath,
                 label: int = Path(ge=1, le=255)) -> dict:
    try:
        material = Material(**body.model_dump())
    except ValueError as exc:
        raise ApiError(422, str(exc)) from None
    s = _plane(request).set_material(session_id, label, material)
    return {"label": label, **asdict(s.materials[label])}


@router.patch("/sessions/{session_id}/materials/{label}")
def patch_material(body: MaterialPatch, request: Request, session_id: int = SessionPath,
                   label: int = Path(ge=1, le=255)) -> dict:
    changes = body.model_dump(exclude_none=True)
    s = _plane(request).set_material(session_id, label, None, changes)
    return {"label": label, **asdict(s.materials[label])}


@router.get("/sessions/{session_id}/state")
def get_state(request: Request, session_id: int = SessionPath,
              max_events: int = Query(100, ge=0, le=10_000)) -> dict:
    """Bone version, removed volume per material, forbidden-contact events (the latest
    ``max_events``), counters, tick-time quantiles and the haptic output (coupling stiffness
    and damping in use, the passivity observer's energy, the proxy)."""
    plane = _plane(request)
    state = plane.session_state(session_id, max_events)
    latest = request.app.state.stats.latest
    if latest and session_id in latest["sessions"]:
        s = latest["sessions"][session_id]
        state["tick_p50_us"], state["tick_p99_us"] = s["tick_p50_us"], s["tick_p99_us"]
    return state
