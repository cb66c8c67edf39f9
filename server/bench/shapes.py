"""Burr shapes: the rows ``bench accuracy`` reports per shape — each burr's model (the
revolved grid at its default resolution, on the flat workpiece) against its own converged
reference (``model.reference_shapes``) over the thesis's nine cases, the lowest point 0.5 mm
deep. Fluted burrs are validated against their reference only: no measurement backs them."""

from __future__ import annotations

import math

import numpy as np

from ..model import CuttingParams, thesis_cases
from ..model.reference import _basis
from ..model.reference_shapes import reference_shape_flat
from ..model.revolved import DEFAULT_ELEMENTS, RevolvedModel
from ..model.shapes import Barrel, Burr, BurrShape, Cylinder, Fluted, Sphere, profile_points

#: The burrs measured: a round one and the other shapes, abrasive and fluted.
BURRS = {
    "sphere": Burr(Sphere(2.0)),
    "cylinder-flat": Burr(Cylinder(1.0, 4.0, "flat")),
    "cylinder-round": Burr(Cylinder(1.5, 5.0, "round")),
    "barrel": Burr(Barrel(1.5, 1.0, 4.0)),
    "cylinder-fluted": Burr(Cylinder(1.0, 4.0, "flat"), Fluted(6, 30.0, 5.0, 30.0)),
    "barrel-fluted": Burr(Barrel(1.5, 1.0, 4.0), Fluted(8, -20.0, -5.0, 35.0)),
}
#: Worst force error against the reference at the default resolution.
TARGET_SHAPE_ERROR = 0.005
DEPTH_MM = 0.5


def centre_at_depth(shape: BurrShape, axis: np.ndarray, depth_mm: float) -> np.ndarray:
    """The reference centre that puts the burr's lowest point ``depth_mm`` into the flat
    workpiece's bone (z < 0) with the tool axis ``axis``."""
    e1, e2, e3 = _basis(np.asarray(axis, float))
    down = np.array([0.0, 0.0, -1.0])
    pts = profile_points(shape.profile(), per_arc=4096)
    reach = (pts[:, 0] * math.hypot(down @ e1, down @ e2) + pts[:, 1] * (down @ e3)).max()
    return np.array([0.0, 0.0, reach - depth_mm])


def shape_rows(n_elements: int = DEFAULT_ELEMENTS) -> list[dict]:
    """Per burr: the worst relative force error over the nine cases against its reference."""
    params = CuttingParams()
    rows = []
    for name, burr in BURRS.items():
        model = RevolvedModel(burr, params, n_elements=n_elements)
        worst = 0.0
        for case in thesis_cases():
            pose = (centre_at_depth(burr.shape, case.axis, DEPTH_MM), case.axis,
                    case.feed_velocity_mm_s, case.rpm)
            ref = reference_shape_flat(burr, params, *pose).force_N
            got = model.evaluate(*pose).force_N
            worst = max(worst, float(np.linalg.norm(got - ref) / np.linalg.norm(ref)))
        rows.append({"kind": "shape", "grid": "flat model", "voxel_mm": None, "case": name,
                     "metric": f"worst force error vs its reference, nine cases, "
                               f"{n_elements} elements", "value": worst,
                     "target": TARGET_SHAPE_ERROR, "ok": bool(worst <= TARGET_SHAPE_ERROR)})
    return rows
