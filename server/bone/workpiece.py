"""The voxel bone behind the model's :class:`~burrforce.server.model.Workpiece` interface.

For analysis with :class:`~burrforce.server.model.CuttingModel` (forces from a bone as it is,
without carving it). The hot loop uses :class:`BoneEngine`, which carves and evaluates in one
call. Us and K come from the bone's material table; the scalars the model passes are unused.
"""

from __future__ import annotations

import numpy as np

from ..model.burr import BurrGrid
from ..model.params import CuttingParams
from ..model.workpiece import Workpiece
from .engine import BoneEngine, ShaftParams
from .grid import BoneGrid
from .materials import MaterialTable


class VoxelWorkpiece(Workpiece):
    """A voxel bone the model can evaluate against (read-only: nothing is carved).

    Positions and vectors passed to :meth:`cut` are in the world frame; results come back in
    the world frame too.
    """

    def __init__(self, grid: BoneGrid, materials: MaterialTable | None = None) -> None:
        self.grid = grid
        self.materials = materials if materials is not None else MaterialTable()
        self._engine_key: tuple[float, tuple[int, int, int]] | None = None
        self._engine_for_key: BoneEngine | None = None

    def _engine(self, grid: BurrGrid, radius_mm: float) -> BoneEngine:
        """The engine for this burr radius and resolution (one at a time)."""
        key = (radius_mm, grid.key)
        engine = self._engine_for_key
        if engine is None or key != self._engine_key:
            # The model decides whether the spindle cuts (``cutting``); the engine must not
            # apply a minimum speed of its own, so its minimum is the lowest allowed.
            params = CuttingParams(radius_mm=radius_mm, min_cutting_rpm=1.0)
            engine = BoneEngine(self.grid, self.materials, params,
                                ShaftParams(length_mm=0.0), n_theta=grid.n_theta,
                                n_phi=grid.n_phi, refine=grid.refine)
            self._engine_key, self._engine_for_key = key, engine
        return engine

    def cut(self, grid, radius_mm, centre_mm, axis, feed_mm_s, omega_rad_s, us_n_mm2, k,
            cutting, scratch, out):
        engine = self._engine(grid, radius_mm)
        g = self.grid
        # Spin: engine.step_raw takes rpm with the params' forward convention (Ω = −ω·a).
        rpm = -omega_rad_s * 60.0 / (2.0 * np.pi)
        if not cutting:
            rpm = 0.0  # below the cutting speed: contact only
        elif abs(rpm) < 1.0:
            rpm = 1.0 if rpm >= 0.0 else -1.0
        unit = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
        engine.step_raw(g.to_grid_point(centre_mm), g.to_grid_vector(unit),
                        g.to_grid_vector(feed_mm_s), rpm, carve=False)
        out[:] = engine.out
        if not g.identity_direction:
            for base in (0, 3, 12):
                out[base:base + 3] = g.to_world_vector(out[base:base + 3])
