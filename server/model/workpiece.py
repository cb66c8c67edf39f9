"""The material interface: how much bone is where each burr element is going.

A workpiece owns its geometry and one fused numba kernel that, in a single call, gives every
burr element its fraction in bone and accumulates the cut (``kernels.accumulate``). The voxel
bone implements the same interface with a density-driven fraction.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from .burr import BurrGrid
from .kernels_flat import cut_flat


class Workpiece(ABC):
    """Bone the burr can cut. Implementations fill an (N_OUT,) result vector (kernels.OUT_*)."""

    @abstractmethod
    def cut(
        self,
        grid: BurrGrid,
        radius_mm: float,
        centre_mm: np.ndarray,
        axis: np.ndarray,
        feed_mm_s: np.ndarray,
        omega_rad_s: float,
        us_n_mm2: float,
        k: float,
        cutting: bool,
        scratch: np.ndarray,
        out: np.ndarray,
    ) -> None:
        """Evaluate the model for one burr pose (one kernel call).

        ``centre_mm``, ``axis``, ``feed_mm_s``: float64 arrays of shape (3,) in the workpiece's
        (world) frame. ``omega_rad_s`` is signed along the axis (forward spin is negative).
        When ``cutting`` is False only the contact area is reported.
        """


class FlatWorkpiece(Workpiece):
    """A bone half-space with a flat surface (the thesis's workpiece).

    Args:
        surface_point_mm: any point of the bone surface, mm. Default the origin.
        surface_normal: outward normal of the surface (away from the bone). Default +z, so the
            bone fills z < 0 as in model.md.
    """

    def __init__(
        self,
        surface_point_mm: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 0.0),
        surface_normal: tuple[float, float, float] | np.ndarray = (0.0, 0.0, 1.0),
    ) -> None:
        point = np.asarray(surface_point_mm, dtype=np.float64).reshape(-1)
        normal = np.asarray(surface_normal, dtype=np.float64).reshape(-1)
        if point.shape != (3,) or normal.shape != (3,):
            raise ValueError("surface_point_mm and surface_normal must each have 3 components")
        if not (np.isfinite(point).all() and np.isfinite(normal).all()):
            raise ValueError("surface_point_mm and surface_normal must be finite")
        length = float(np.linalg.norm(normal))
        if length < 1e-12:
            raise ValueError("surface_normal must not be zero")
        self.surface_point_mm = point
        self.surface_normal = normal / length

    def __repr__(self) -> str:
        return (f"FlatWorkpiece(surface_point_mm={self.surface_point_mm.tolist()}, "
                f"surface_normal={self.surface_normal.tolist()})")

    def cut(self, grid, radius_mm, centre_mm, axis, feed_mm_s, omega_rad_s, us_n_mm2, k,
            cutting, scratch, out):
        cut_flat(grid.cos_theta, grid.sin_theta, grid.cos_phi, grid.sin_phi, grid.d_theta,
                 grid.d_phi, grid.cos_sub_t, grid.sin_sub_t, grid.cos_sub_p, grid.sin_sub_p,
                 radius_mm, centre_mm, axis, feed_mm_s, omega_rad_s, us_n_mm2, k,
                 cutting, self.surface_point_mm, self.surface_normal, scratch, out)
