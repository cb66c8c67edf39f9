"""Plunges for ``burrforce bench accuracy``: removal against the analytic cap and force growing
with depth, for the flat model and the voxel bone (issue 21, item 2).

A plunge feeds the burr straight into the workpiece's top (v_f = −v·ẑ) with its axis at α to
the surface (axis (−cos α, 0, sin α); at 90° the cut cap sits on the spin pole). Every part of
the cap then cuts, so the exact removal rate is v·π·(2Rh − h²) (``plunge_removal_mm3_s``).
Each depth is one evaluation of an uncarved pose (the voxel bone with ``carve=False``), so the
curves are the model's, not a carving history's.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..bone import BoneEngine, ShaftParams
from ..model import CuttingModel, CuttingParams
from ..model.burr import DEFAULT_N_THETA
from ..model.kernels import OUT_FORCE, OUT_VOLUME_RATE
from ..model.reference import plunge_removal_mm3_s
from .groove import GROOVE_BLOCK_HI_MM, GROOVE_BLOCK_LO_MM, groove_block, oblique_rotation

PLUNGE_RPM = 60000.0
PLUNGE_FEED_MM_S = 1.0
#: Depths at which removal is compared with the analytic cap, mm.
REMOVAL_DEPTHS_MM = (1e-6, 1e-3, 1e-2, 0.1, 1.0)
ANGLES_DEG = (0.0, 10.0, 30.0, 45.0, 60.0, 90.0)
#: The fine sweep: geometric from 1 µm to 3.5 mm.
SWEEP_FROM_MM = 1e-3
SWEEP_TO_MM = 3.5
#: A step counts as a decrease below this relative change (float noise is ~1e-15).
DECREASE_TOL = 1e-9


def _axis(angle_deg: float) -> np.ndarray:
    alpha = math.radians(angle_deg)
    return np.array([-math.cos(alpha), 0.0, math.sin(alpha)])


def _decreases(values: np.ndarray) -> tuple[int, float]:
    """Steps that fall (relative change below −DECREASE_TOL), and the worst relative step."""
    steps = np.diff(values) / np.maximum(np.abs(values[1:]), 1e-300)
    return int(np.sum(steps < -DECREASE_TOL)), float(min(steps.min(), 0.0))


class _Flat:
    """The flat model: bone in z < 0."""

    def __init__(self, n_theta: int) -> None:
        self.model = CuttingModel(CuttingParams(), n_theta=n_theta)
        self.radius = self.model.params.radius_mm

    def evaluate(self, angle_deg: float, depth_mm: float) -> tuple[float, float]:
        r = self.model.evaluate(np.array([0.0, 0.0, self.radius - depth_mm]), _axis(angle_deg),
                                np.array([0.0, 0.0, -PLUNGE_FEED_MM_S]), PLUNGE_RPM)
        return r.normal_N, r.removed_mm3_s


class _Voxel:
    """The voxel engine on the groove bench's block (top at z = 0), plunging at its middle."""

    def __init__(self, voxel_mm: float, oblique: bool, n_theta: int) -> None:
        self.grid = groove_block(voxel_mm, oblique_rotation() if oblique else None)
        self.engine = BoneEngine(self.grid, shaft=ShaftParams(length_mm=0.0), n_theta=n_theta)
        self.radius = self.engine.params.radius_mm
        mid = 0.5 * (np.asarray(GROOVE_BLOCK_LO_MM) + np.asarray(GROOVE_BLOCK_HI_MM))
        self.xy = mid[:2]
        self.feed_g = self.grid.to_grid_vector(np.array([0.0, 0.0, -PLUNGE_FEED_MM_S]))

    def evaluate(self, angle_deg: float, depth_mm: float) -> tuple[float, float]:
        centre = np.array([self.xy[0], self.xy[1], self.radius - depth_mm])
        self.engine.step_raw(self.grid.to_grid_point(centre),
                             self.grid.to_grid_vector(_axis(angle_deg)), self.feed_g,
                             PLUNGE_RPM, carve=False)
        # Along the block's true normal (world +z): what the hand pushing the burr in feels.
        # (The estimated ŝ of the REPLY's components wanders by 2–3° with depth on an oblique
        # grid, from the partial-volume faces' trilinear gradient.)
        force = self.grid.to_world_vector(self.engine.out[OUT_FORCE:OUT_FORCE + 3])
        return float(force[2]), float(self.engine.out[OUT_VOLUME_RATE])


def plunge_rows(
    voxel_mm: float = 0.1,
    angles_deg: Sequence[float] = ANGLES_DEG,
    removal_depths_mm: Sequence[float] = REMOVAL_DEPTHS_MM,
    sweep_depths: int = 200,
    n_theta: int = DEFAULT_N_THETA,
    voxel: bool = True,
) -> list[dict]:
    """One row per (model, grid, tool angle) for the accuracy bench's "plunge" table.

    Args:
        voxel_mm: voxel size of the bone, mm.
        angles_deg: tool angles to the surface, degrees (90: the axis is the surface normal).
        removal_depths_mm: depths where removal is compared with the analytic cap, mm.
        sweep_depths: depths of the fine sweep (geometric, 1 µm to 3.5 mm).
        n_theta: burr resolution (latitude bands).
        voxel: also measure the voxel bone (aligned and oblique grids).

    Returns:
        dicts with ``model`` ("flat" or "voxel"), ``grid`` ("–" for the flat model,
        "aligned" or "oblique"), ``voxel_mm`` (None for flat), ``angle_deg``,
        ``removal_error_rel``: {depth_mm: removal / analytic cap − 1}, ``normal_decreases`` and
        ``removal_decreases``: how many of the sweep's steps fall (out of ``steps``), and
        ``worst_normal_step_rel``, ``worst_removal_step_rel``: the largest relative fall (≤ 0).
    """
    sweep = np.geomspace(SWEEP_FROM_MM, SWEEP_TO_MM, sweep_depths)
    evaluators: list[tuple[str, str, float | None, object]] = [
        ("flat", "–", None, _Flat(n_theta))]
    if voxel:
        evaluators += [("voxel", kind, voxel_mm, _Voxel(voxel_mm, kind == "oblique", n_theta))
                       for kind in ("aligned", "oblique")]
    rows = []
    for model, grid, size, ev in evaluators:
        radius = ev.radius  # type: ignore[attr-defined]
        for angle in angles_deg:
            errors = {}
            for depth in removal_depths_mm:
                removed = ev.evaluate(angle, depth)[1]  # type: ignore[attr-defined]
                exact = plunge_removal_mm3_s(radius, depth, PLUNGE_FEED_MM_S)
                errors[float(depth)] = removed / exact - 1.0
            curve = np.array([ev.evaluate(angle, h) for h in sweep])  # type: ignore[attr-defined]
            normal_falls, normal_worst = _decreases(curve[:, 0])
            removal_falls, removal_worst = _decreases(curve[:, 1])
            rows.append({
                "model": model, "grid": grid, "voxel_mm": size, "angle_deg": float(angle),
                "n_theta": n_theta, "removal_error_rel": errors,
                "steps": len(sweep) - 1,
                "normal_decreases": normal_falls, "worst_normal_step_rel": normal_worst,
                "removal_decreases": removal_falls, "worst_removal_step_rel": removal_worst,
            })
    return rows
