"""Haptic devices and actuators on the server's machine: list, attach, status, detach."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter

from ..devices.loop import DeviceLoopConfig
from ..devices.mapping import WorkspaceMap, bone_top_centre
from ..devices.registry import HAPTIC, PATH_OPTIONS, check_spec, format_spec, parse_spec
from .deps import PlaneDep, SessionPath
from .errors import ApiError, Invalid
from .models import DeviceAttach, Parameters

router = APIRouter(tags=["devices"])


def confined(spec: str, data_dir: Path) -> str:
    """``spec`` with its file options (``registry.PATH_OPTIONS``: a WAV to write, the Falcon's
    firmware to read) resolved inside the server's data directory: over REST a client names
    files there, never elsewhere on the server's machine (422 otherwise)."""
    name, options = parse_spec(spec)
    root = data_dir.expanduser().resolve()
    for key in PATH_OPTIONS:
        if key in options:
            path = (root / str(options[key])).resolve()
            if not path.is_relative_to(root):
                raise Invalid(f"{key}={options[key]!r}: over REST, files are named "
                              f"relative to the server's data directory ({root}) and "
                              "must stay inside it")
            options[key] = str(path)
    return format_spec(name, options)


@router.get("/devices")
def list_devices() -> list[dict]:
    """Every supported haptic device and actuator back-end, whether its requirements are
    installed, and the units detected on this machine (USB, sound cards), with the udev rule
    a detected but inaccessible device needs."""
    from ..devices.discovery import list_devices as discover

    return discover()


@router.put("/sessions/{session_id}/device")
def attach_device(plane: PlaneDep, body: DeviceAttach,
                  session_id: int = SessionPath) -> dict:
    """Drive a local device from this session: a device loop (its own process) streams the
    device's pose into the session and renders the coupling model at the device's servo
    rate, with the watchdog. The session's output becomes coupled for the device's profile
    unless a device profile is already set. Returns the loop's status (``homing`` while the
    user homes a Falcon); 422 with the reason if the device cannot be opened here (not plugged
    in, no permission, a vendor library or the Falcon's firmware missing), 409 if the session
    already drives one."""
    session = plane.ready(session_id)
    try:
        device = confined(body.device, plane.data_dir)
        actuator = confined(body.actuator, plane.data_dir) if body.actuator else None
        name, options = check_spec(device, "haptic")
        if actuator:
            check_spec(actuator, "actuator")
    except ValueError as exc:
        raise Invalid(str(exc)) from None
    # The session renders the coupled output for the device's profile (unless it already has
    # a device profile) before the loop's first pose; undone if the device cannot be opened.
    profile = HAPTIC[name].profile_for(options)
    set_profile = session.device is None and profile is not None
    if set_profile:
        plane.update_parameters(session_id, Parameters(device=profile))

    def make_config(session, host: str, port: int) -> DeviceLoopConfig:
        placement = body.placement_mm or bone_top_centre(session.bone_info)
        c = session.config
        return DeviceLoopConfig(
            device=device, host=host, port=port, session=session.id,
            key_hex=session.key_hex, frame=c.frame,
            placement_position=tuple(c.placement_position),
            placement_orientation=tuple(c.placement_orientation),
            workspace=WorkspaceMap(tuple(placement), tuple(body.rotation),
                                   body.workspace_scale),
            actuator=actuator, rpm=body.rpm, spindle=body.spindle, home=body.home,
            stale_s=body.stale_ms * 1e-3)

    try:
        return plane.attach_device(session_id, make_config).status()
    except ApiError:
        if set_profile:
            plane.update_parameters(session_id, Parameters(device="none"))
        raise


@router.get("/sessions/{session_id}/device")
def device_status(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    """The device loop's state (starting, homing, running, stopped, failed), counters
    (cycles, overruns, saturations, watchdog trips, poses, replies), measured servo rate and
    period/round-trip percentiles, position, force, vibration, and its recent events."""
    plane.get(session_id)
    return plane.devices.get(session_id).status()


@router.delete("/sessions/{session_id}/device")
def detach_device(plane: PlaneDep, session_id: int = SessionPath) -> dict:
    """Stop the device loop (the device is sent zero force and released); returns its final
    status."""
    return plane.devices.detach(session_id)
