"""The resistive cutting force of a burr, the thesis's sphere or any other shape (model.md,
thesis eqs. 2–7): the entry point most callers want."""

from __future__ import annotations

import numpy as np

from .burr import DEFAULT_N_THETA, DEFAULT_REFINE, BurrGrid
from .kernels import new_buffer, new_scratch
from .params import CuttingParams
from .pose import MAX_POSITION_MM, MAX_RPM, MAX_SPEED_MM_S, RPM_TO_RAD_S, check_pose
from .result import CuttingResult, result_from_out
from .revolved import RevolvedModel
from .shapes import Burr
from .workpiece import FlatWorkpiece, Workpiece

# Re-exported: these names were defined here before the result and the pose checks moved to
# result.py and pose.py (revolved.py needs them, and this module needs revolved.py).
__all__ = ["MAX_POSITION_MM", "MAX_RPM", "MAX_SPEED_MM_S", "RPM_TO_RAD_S", "CuttingModel",
           "CuttingResult", "check_pose", "result_from_out"]


class CuttingModel:
    """Evaluates the cutting force of one burr against one workpiece.

    Owns the burr discretization (tables built once per resolution; they are unit-sphere tables,
    so changing R does not rebuild them) and preallocated buffers, so an evaluation allocates
    only its result.

    The burr is ``params.shape``. A round abrasive burr integrates on the sphere's grid; any
    other burr (``params.burr``: a cylinder, a barrel, a fluted burr) is computed by a
    :class:`~.revolved.RevolvedModel` on the flat workpiece with about ``n_theta·n_phi``
    elements (its own near-square layout; the default 24 × 48 is its default 1152) and the
    same ``refine``, so both classes give the same results for it.

    Args:
        params: model parameters (Us, K, R, spin, minimum cutting rpm, burr).
        workpiece: the bone. Default the thesis's flat workpiece, bone in z < 0.
        n_theta, n_phi: burr resolution (latitude bands, longitude sectors; n_phi = 2·n_theta
            by default).
        refine: elements the bone surface crosses are split refine×refine.

    Raises:
        ValueError: a burr that is not round and abrasive on a workpiece other than
            :class:`~.workpiece.FlatWorkpiece` (a voxel bone evaluates a shaped burr through
            ``bone.BoneEngine``), here or at an evaluation after ``params`` changed.
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
        #: The model of a burr that is not round and abrasive, and what it was built for.
        self._shaped: RevolvedModel | None = None
        self._shaped_key: tuple[object, ...] = ()
        if self.params.burr is not None:  # a burr this workpiece cannot take fails here
            self._shaped_model(self.params.burr)

    def _shaped_model(self, burr: Burr) -> RevolvedModel:
        """The model computing ``burr`` (``params.burr``), rebuilt when the burr, K or the
        resolution changes; it always runs with the current params and workpiece."""
        if not isinstance(self.workpiece, FlatWorkpiece):
            kind = f"{type(burr.cutter).__name__.lower()} {burr.shape.kind}"
            raise ValueError(
                f"CuttingModel computes a {kind} burr on a FlatWorkpiece only (by "
                f"RevolvedModel); {type(self.workpiece).__name__} takes the round abrasive "
                "burr: on a voxel bone, use bone.BoneEngine with these params")
        n_elements = self.grid.n_theta * self.grid.n_phi
        key = (burr, self.params.k, n_elements, self.grid.refine)
        if self._shaped is None or key != self._shaped_key:
            self._shaped = RevolvedModel(burr, self.params, self.workpiece, n_elements,
                                         self.grid.refine)
            self._shaped_key = key
        self._shaped.params = self.params
        self._shaped.workpiece = self.workpiece
        return self._shaped

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
        if p.burr is not None:
            return self._shaped_model(p.burr).evaluate_raw(centre_mm, axis, feed_mm_s, rpm)
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
