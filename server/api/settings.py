"""A session's settings after a change, validated: pure functions from the settings it has and
the change asked for to the settings it would have. Nothing here touches a session or the hot
loop; a change that does not fit raises before anything changed.

Raises :class:`~.errors.Invalid` (a value that does not fit) and :class:`~.errors.NotFound`
(a material label the bone lacks), never anything HTTP.
"""

from __future__ import annotations

from dataclasses import replace

from ..bone import Material, MaterialTable
from ..bone.engine import check_burr
from ..haptics import PROFILES, DeviceProfile
from ..model.params import CuttingParams
from ..model.shapes import Burr, Sphere
from .errors import Invalid, NotFound
from .models import Parameters
from .sessions import Settings


def settle(current: Settings, p: Parameters,
           spacing_mm: tuple[float, ...] = (0.0,)) -> Settings:
    """``current`` with the fields ``p`` sets, all checked together: the burr against the
    bone's voxels (``spacing_mm``, mm; ``(0.0,)`` before a bone is loaded), the primary
    material against the bone's table, Us/K against the material.

    Raises:
        Invalid: a field does not fit (the message says which and why).
    """
    try:
        params = current.params.with_(**{k: v for k, v in (
            ("spin", p.spin), ("min_cutting_rpm", p.min_cutting_rpm)) if v is not None})
        params = _with_burr(params, p)
        shaft = replace(current.shaft, **{k: v for k, v in (
            ("radius_mm", p.shaft_radius_mm), ("length_mm", p.shaft_length_mm),
            ("stiffness_n_mm3", p.shaft_stiffness_n_mm3)) if v is not None})
        harmonic = p.harmonic
        if harmonic is None and params.shape.cutter != current.params.shape.cutter:
            harmonic = params.shape.cutter.harmonic  # flutes set the tooth frequency
        vibration = replace(current.vibration, **{k: v for k, v in (
            ("fd_N", p.fd_N), ("g", p.g), ("harmonic", harmonic)) if v is not None})
        config = replace(current.config, **{k: v for k, v in (
            ("frame", p.frame), ("tool_axis", p.tool_axis),
            ("placement_position", p.placement_position),
            ("placement_orientation", p.placement_orientation)) if v is not None})
        device = _device(current.device, p)
        check_burr(spacing_mm, params, shaft)
    except (TypeError, ValueError) as exc:
        raise Invalid(str(exc)) from None
    materials = current.materials
    primary = current.primary_label
    if p.primary_material is not None:
        if materials is not None and p.primary_material not in materials:
            raise Invalid(f"the bone has no material with label {p.primary_material}")
        primary = p.primary_material
    overrides = dict(current.overrides)
    us_k = {k: v for k, v in (("us_n_mm2", p.us_n_mm2), ("k", p.k)) if v is not None}
    if us_k:
        target = primary if materials is not None else None  # None: the primary, on load
        if materials is not None and primary is None:
            raise Invalid("the bone has no cuttable material to set Us/K on")
        overrides[target] = {**overrides.get(target, {}), **us_k}
        if materials is not None:
            try:
                materials = with_overrides(materials, primary, {target: us_k})
            except ValueError as exc:
                raise Invalid(str(exc)) from None
    return replace(current, params=params, shaft=shaft, vibration=vibration, config=config,
                   device=device, materials=materials, primary_label=primary,
                   overrides=overrides)


def with_material(current: Settings, label: int, material: Material | None,
                  changes: dict | None = None) -> Settings:
    """``current`` with material ``label`` set to ``material`` (None: its fields changed by
    ``changes``), remembered in the overrides so the next bone gets it too.

    Raises:
        NotFound: ``changes`` for a label the bone lacks.
        Invalid: a value the material table refuses.
    """
    assert current.materials is not None
    table = current.materials.copy()
    if material is None and label not in table:
        raise NotFound(f"no material with label {label}")
    try:
        if material is not None:
            table.set(label, material)
        else:
            table.update(label, **(changes or {}))
    except (KeyError, ValueError) as exc:
        raise Invalid(str(exc.args[0]) if exc.args else str(exc)) from None
    m = table[label]
    overrides = {**current.overrides, label: {
        "name": m.name, "us_n_mm2": m.us_n_mm2, "k": m.k, "forbidden": m.forbidden}}
    return replace(current, materials=table, overrides=overrides)


def default_primary(materials: MaterialTable) -> int | None:
    """Label 1 if the bone has it (the thesis's cortical bone in every built-in table), else
    its first material that is not forbidden."""
    labels = [label for label, m in materials if not m.forbidden]
    if 1 in labels:
        return 1
    return labels[0] if labels else None


def with_overrides(materials: MaterialTable, primary: int | None,
                   overrides: dict) -> MaterialTable:
    """A copy of ``materials`` with the REST changes applied (key None: the primary
    material). Labels the bone does not have get the full material if one was given.
    ValueError says what does not fit."""
    table = materials.copy()
    for label, changes in overrides.items():
        label = primary if label is None else label
        if label is None:
            continue
        if label in table:
            table.update(label, **changes)
        elif {"name", "us_n_mm2", "k"} <= set(changes):
            table.set(label, Material(**changes))
    return table


def _with_burr(params: CuttingParams, p: Parameters) -> CuttingParams:
    """``params`` with ``p``'s burr and radius: a burr replaces the shape (its largest radius
    becomes radius_mm, which must agree if given too); radius_mm alone resizes a round burr.
    ValueError says what does not fit."""
    if p.burr is not None:
        burr = Burr.from_dict(p.burr)
        new = params.with_(burr=burr, radius_mm=burr.shape.max_radius_mm)
        if p.radius_mm is not None and abs(p.radius_mm - new.radius_mm) > 1e-9:
            raise ValueError(f"radius_mm {p.radius_mm} disagrees with the burr's shape (largest "
                             f"radius {new.radius_mm} mm): give the sizes in burr.shape only")
        return new
    if p.radius_mm is None:
        return params
    shape = params.shape
    if abs(p.radius_mm - params.radius_mm) <= 1e-9:
        return params  # re-sent as it is (any shape)
    if not isinstance(shape.shape, Sphere):
        raise ValueError(f"radius_mm resizes a round burr; this one is a {shape.shape.kind}: "
                         f"give its sizes in burr.shape")
    return params.with_(burr=Burr(Sphere(p.radius_mm), shape.cutter), radius_mm=p.radius_mm)


def _device(current: DeviceProfile | None, p: Parameters) -> DeviceProfile | None:
    """The device profile after ``p`` (parameters.device and device_limits)."""
    limits = {} if p.device_limits is None else p.device_limits.model_dump(exclude_none=True)
    name = p.device
    if name is None and not limits:
        return current
    if name == "none":
        if limits:
            raise ValueError("device_limits need a device profile, not none")
        return None
    if name is None or name == "custom":
        base = current if current is not None else PROFILES["generic"]
        if name == "custom" and not limits and current is None:
            raise ValueError("a custom device needs device_limits")
        return base.customized(**limits) if limits else base
    return PROFILES[name].customized(**limits) if limits else PROFILES[name]
