"""The resistive cutting force of a spinning spherical burr (model.md, thesis eqs. 2–7)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .burr import DEFAULT_N_THETA, DEFAULT_REFINE, BurrGrid
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
    new_buffer,
    new_scratch,
)
from .params import CuttingParams
from .workpiece import FlatWorkpiece, Workpiece

RPM_TO_RAD_S = 2.0 * math.pi / 60.0
# Plausibility bounds at the API edge: far beyond any burr, far below float overflow.
MAX_POSITION_MM = 1e6
MAX_SPEED_MM_S = 1e7
MAX_RPM = 1e7


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


class CuttingModel:
    """Evaluates the cutting force of one burr against one workpiece.

    Owns the burr discretization (tables built once per resolution; they are unit-sphere tables,
    so changing R does not rebuild them) and preallocated buffers, so an evaluation allocates
    only its result.

    Args:
        params: model parameters (Us, K, R, spin, minimum cutting rpm).
        workpiece: the bone. Default the thesis's flat workpiece, bone in z < 0.
        n_theta, n_phi: burr resolution (latitude bands, longitude sectors; n_phi = 2·n_theta
            by default).
        refine: elements the bone surface crosses are split refine×refine.
    """

    def __init__(
        self,
        params: CuttingParams | None = None,
        workpiece: Workpiece | None = None,
        n_theta: int = DEFAULT_N_THETA,
        n_phi: int | None = None,
        refine: int = DEFAULT_REFINE,
    ) -> None:
        self.params = params if params is not None else CuttingParams()
        self.workpiece = workpiece if workpiece is not None else FlatWorkpiece()
        self.grid = BurrGrid.build(n_theta, n_phi, refine)
        self._scratch = new_scratch()
        self._out = new_buffer()

    def set_resolution(self, n_theta: int, n_phi: int | None = None,
                       refine: int = DEFAULT_REFINE) -> None:
        """Rebuild the burr tables only if the resolution changed."""
        wanted_phi = 2 * n_theta if n_phi is None else n_phi
        if (n_theta, wanted_phi, refine) != self.grid.key:
            self.grid = BurrGrid.build(n_theta, wanted_phi, refine)

    def omega_rad_s(self, rpm: float) -> float:
        """Signed angular speed along the tool axis: Ω = omega·a. The sign of rpm reverses spin."""
        return self.params.spin_sign * rpm * RPM_TO_RAD_S

    def is_cutting_speed(self, rpm: float) -> bool:
        return abs(rpm) >= self.params.min_cutting_rpm

    def evaluate_raw(self, centre_mm: np.ndarray, axis: np.ndarray, feed_mm_s: np.ndarray,
                     rpm: float) -> np.ndarray:
        """Fast path: the kernel's (N_OUT,) result vector (kernels.OUT_*), reused between calls
        (so use one model per thread, although the kernel releases the GIL).

        Inputs must already be validated float64 arrays of shape (3,) — finite, within the
        plausibility bounds, the axis non-zero (the kernel normalises it) — as :meth:`evaluate`
        does; the caller (the hot loop) validates them once at the edge.
        """
        p = self.params
        self.workpiece.cut(self.grid, p.radius_mm, centre_mm, axis, feed_mm_s,
                           self.omega_rad_s(rpm), p.us_n_mm2, p.k, self.is_cutting_speed(rpm),
                           self._scratch, self._out)
        return self._out

    def evaluate(
        self,
        centre_mm: np.ndarray | tuple[float, float, float],
        axis: np.ndarray | tuple[float, float, float],
        feed_mm_s: np.ndarray | tuple[float, float, float],
        rpm: float,
    ) -> CuttingResult:
        """Resistive force for a burr at ``centre_mm`` (mm) with tool axis ``axis`` (toward the
        handle, any non-zero length), moving at ``feed_mm_s`` (mm/s) relative to the bone and
        spinning at ``rpm`` (signed: a negative value reverses the configured spin).

        Raises:
            ValueError: on non-finite or implausibly large inputs (beyond ±1e6 mm, 1e7 mm/s or
                1e7 rpm), wrong shapes or a zero axis.
        """
        return result_from_out(self.evaluate_raw(*check_pose(centre_mm, axis, feed_mm_s, rpm)))


def check_pose(centre_mm: object, axis: object, feed_mm_s: object,
               rpm: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Validated (centre, axis, feed, rpm): float64 (3,) arrays and a float, the axis rescaled
    (``check_axis``). Raises ValueError naming the bad input."""
    centre = check_vec3("centre_mm", centre_mm, MAX_POSITION_MM)
    ax = check_axis("axis", axis)
    feed = check_vec3("feed_mm_s", feed_mm_s, MAX_SPEED_MM_S)
    rpm = float(rpm)  # type: ignore[arg-type]
    if not abs(rpm) <= MAX_RPM:
        raise ValueError(f"rpm must be finite and within ±{MAX_RPM:g}, got {rpm}")
    return centre, ax, feed, rpm


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


def check_vec3(name: str, value: object, limit: float) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {arr.shape}")
    if not (np.abs(arr) <= limit).all():  # also false for NaN
        raise ValueError(f"{name} must be finite and within ±{limit:g}, got {arr.tolist()}")
    return arr


def check_axis(name: str, value: object) -> np.ndarray:
    """``value`` rescaled so its largest component is ±1: the kernel normalises it, and any
    finite, non-zero magnitude (1e-170 or 1e200) survives that without under- or overflow."""
    arr = check_vec3(name, value, math.inf)
    scale = float(np.abs(arr).max())
    if scale == 0.0:
        raise ValueError(f"{name} must not be zero")
    return arr / scale
