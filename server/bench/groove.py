"""A steady groove through the workpiece block at 1 kHz: the voxel engine's accuracy test bed.

Shared by ``burrforce bench accuracy`` and the tests.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass

import numpy as np

from ..bone import BoneEngine, ShaftParams, workpiece_block
from ..bone.grid import BoneGrid
from ..model.cases import CuttingCase
from ..model.kernels import OUT_FORCE, OUT_POWER

#: The oblique grid: rotated 20° about x, then 15° about y, then 10° about z, so every face of
#: the block cuts its voxels at an angle (as a scanned bone's surface does).
OBLIQUE_EULER_XYZ_DEG = (20.0, 15.0, 10.0)


def oblique_rotation() -> np.ndarray:
    """(3, 3) rotation of the oblique grid (:data:`OBLIQUE_EULER_XYZ_DEG`)."""
    rot = np.eye(3)
    for axis, deg in zip("xyz", OBLIQUE_EULER_XYZ_DEG, strict=True):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        r = {"x": [[1, 0, 0], [0, c, -s], [0, s, c]], "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
             "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]]}[axis]
        rot = np.asarray(r) @ rot
    return rot


#: A 12 × 12 × 4 mm block (top at z = 0) is enough for a few-mm groove in any direction.
GROOVE_BLOCK_LO_MM = (0.0, 0.0, -4.0)
GROOVE_BLOCK_HI_MM = (12.0, 12.0, 0.0)
#: Faces fall inside voxels, not on their boundaries.
GROOVE_OFFSET_VOXELS = (0.31, 0.17, 0.43)


@dataclass(frozen=True)
class GrooveRun:
    """Per-tick records of a groove. Arrays have one entry per tick.

    Attributes:
        force_N: (n, 3) cutting force, world frame.
        power_W: (n,) spindle power.
        tick_ns: (n,) wall time of each tick (carve + force, one ``step_raw``), ns.
        steady: boolean mask of the ticks after the warm-up.
        removal_energy_J: Σ Us × removed volume at the end.
        dt_s: tick period.
    """

    force_N: np.ndarray
    power_W: np.ndarray
    tick_ns: np.ndarray
    steady: np.ndarray
    removal_energy_J: float
    dt_s: float

    @property
    def magnitude_N(self) -> np.ndarray:
        return np.linalg.norm(self.force_N, axis=1)

    @property
    def spindle_energy_J(self) -> float:
        """∫ P dt (rectangle rule, one tick per sample)."""
        return float(self.power_W.sum() * self.dt_s)


def groove_block(voxel_mm: float, direction: np.ndarray | None = None) -> BoneGrid:
    return workpiece_block(voxel_mm, lo_mm=GROOVE_BLOCK_LO_MM, hi_mm=GROOVE_BLOCK_HI_MM,
                           margin_mm=1.0, offset_voxels=GROOVE_OFFSET_VOXELS,
                           direction=direction)


def run_groove(
    case: CuttingCase,
    grid: BoneGrid,
    n_theta: int,
    warmup_mm: float = 0.5,
    measure_mm: float = 3.0,
    start_mm: np.ndarray | None = None,
    dt_s: float = 1e-3,
) -> GrooveRun:
    """Plough a straight groove with the case's burr pose, depth, feed and spindle speed.

    By default the burr starts embedded in the block (its first tick carves its own cap) with
    the path centred on the block, so the cutting front is steady after a few ticks; the
    first ``warmup_mm`` of travel are excluded from ``steady`` all the same. ``start_mm``
    places the first burr centre's (x, y) elsewhere (e.g. outside the block, for an energy
    balance over a whole groove).
    """
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0), n_theta=n_theta)
    engine.warm_up()
    velocity = case.feed_velocity_mm_s
    direction = case.feed_direction / np.linalg.norm(case.feed_direction)
    total_mm = warmup_mm + measure_mm
    if start_mm is None:
        mid = 0.5 * (np.asarray(GROOVE_BLOCK_LO_MM) + np.asarray(GROOVE_BLOCK_HI_MM))
        start = np.array([mid[0], mid[1], 0.0]) - 0.5 * total_mm * direction
    else:
        start = np.array([start_mm[0], start_mm[1], 0.0])
    start = start + case.centre_mm
    n = round(total_mm / (case.feed_mm_s * dt_s))
    steady = np.arange(n) * case.feed_mm_s * dt_s >= warmup_mm
    axis_g = grid.to_grid_vector(case.axis / np.linalg.norm(case.axis))
    feed_g = grid.to_grid_vector(velocity)
    force = np.empty((n, 3))
    power = np.empty(n)
    tick_ns = np.empty(n, dtype=np.int64)
    clock = time.perf_counter_ns
    enabled = gc.isenabled()
    gc.disable()
    try:
        for i in range(n):
            centre_g = grid.to_grid_point(start + velocity * (i * dt_s))
            t0 = clock()
            engine.step_raw(centre_g, axis_g, feed_g, case.rpm)
            tick_ns[i] = clock() - t0
            force[i] = engine.out[OUT_FORCE:OUT_FORCE + 3]
            power[i] = engine.out[OUT_POWER] * 1e-3
    finally:
        if enabled:
            gc.enable()
    return GrooveRun(grid.to_world_vector(force.T).T, power, tick_ns, steady,
                     engine.removal_energy_J(), dt_s)
