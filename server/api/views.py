"""How a session looks from outside: the JSON views of a session and of its parameters, shared
by the routes and the journal (pure functions of a session)."""

from __future__ import annotations

from ..model.shapes import profile_points
from .sessions import ManagedSession


def session_view(s: ManagedSession, address: tuple[str, int] | None, device_attached: bool,
                 key: bool = False) -> dict:
    """A session as ``GET /v1/sessions/ID`` shows it (``key``: with its key, which only its
    creation answers with); ``address``: its worker's UDP endpoint; ``device_attached``:
    whether a local device loop drives it."""
    host, port = address or ("", 0)
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
        "device_attached": device_attached,
        "recording": s.recording["name"] if s.recording else None,
        "created": s.created_s,
        "journal": s.journal.view(),
    }
    if key:
        view["key"] = s.key_hex
    return view


def parameters_view(s: ManagedSession) -> dict:
    """A session's parameters as ``GET /v1/sessions/ID/parameters`` shows them (the journal
    keeps the same)."""
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
