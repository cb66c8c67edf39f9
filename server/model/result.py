"""What one evaluation of the cutting model reports, for any burr shape (model.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .kernels import (
    OUT_COMPONENTS,
    OUT_CONTACT_AREA,
    OUT_COUNT,
    OUT_CUT_AREA,
    OUT_FORCE,
    OUT_POWER,
    OUT_SPEED_AREA,
    OUT_SURFACE_NORMAL,
    OUT_TORQUE,
    OUT_VOLUME_RATE,
)


@dataclass(frozen=True)
class CuttingResult:
    """One evaluation of the model. Vectors are float64 arrays of shape (3,), world frame.

    Attributes:
        force_N: force of the bone ON the burr (what the hand feels), N.
        feed_N, lateral_N, normal_N: F·f̂, F·(ŝ×f̂), F·ŝ with f̂ the feed direction and ŝ the
            outward bone-surface normal at the cut (model.md); lateral is positive to the left
            of the feed seen from outside the bone. Feed and lateral are zero without feed.
            The axes are orthonormal when the feed lies in the surface; for a plunging feed
            they are the thesis's projections, not a basis.
        torque_Nmm: reaction torque on the burr about its centre, N·mm. Its component along the
            tool axis is the spindle load torque.
        power_W: spindle power spent cutting, W (= Us × removed_mm3_s, exactly).
        removed_mm3_s: removed-volume rate, mm³/s.
        cutting_elements: number of burr elements that cut.
        mean_speed_m_s: area-weighted mean surface speed |v_t| over the cutting zone, m/s
            (0 when nothing cuts).
        cutting: the spindle turns fast enough to cut and some element cuts.
        contact: some part of the burr lies in bone (whether or not it cuts).
        surface_normal: ŝ used for the components.
    """

    force_N: np.ndarray
    feed_N: float
    lateral_N: float
    normal_N: float
    torque_Nmm: np.ndarray
    power_W: float
    removed_mm3_s: float
    cutting_elements: int
    mean_speed_m_s: float
    cutting: bool
    contact: bool
    surface_normal: np.ndarray

    @property
    def force_magnitude_N(self) -> float:
        return float(np.linalg.norm(self.force_N))


def result_from_out(out: np.ndarray) -> CuttingResult:
    """A :class:`CuttingResult` from a kernel's (N_OUT,) result vector (copied)."""
    cut_area = out[OUT_CUT_AREA]
    count = int(out[OUT_COUNT])
    feed_N, lateral_N, normal_N = out[OUT_COMPONENTS:OUT_COMPONENTS + 3].tolist()
    return CuttingResult(
        force_N=out[OUT_FORCE:OUT_FORCE + 3].copy(),
        feed_N=feed_N,
        lateral_N=lateral_N,
        normal_N=normal_N,
        torque_Nmm=out[OUT_TORQUE:OUT_TORQUE + 3].copy(),
        power_W=float(out[OUT_POWER]) * 1e-3,  # N·mm/s → W
        removed_mm3_s=float(out[OUT_VOLUME_RATE]),
        cutting_elements=count,
        mean_speed_m_s=float(out[OUT_SPEED_AREA] / cut_area) * 1e-3 if cut_area > 0 else 0.0,
        cutting=count > 0,
        contact=bool(out[OUT_CONTACT_AREA] > 0.0),
        surface_normal=out[OUT_SURFACE_NORMAL:OUT_SURFACE_NORMAL + 3].copy(),
    )
