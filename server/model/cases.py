"""The thesis's experiment (Table 1) as reproducible cases, with model.md's geometry.

Bone fills z < 0; burr centre at z = R − h; the tool stem lies in the x–z plane and leans back
against the feed: a = (−cos α, 0, sin α). Feed directions: parallel (1, 0, 0), perpendicular
(0, 1, 0), diagonal (1, 1, 0)/√2.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

ORIENTATIONS: dict[str, tuple[float, float, float]] = {
    "parallel": (1.0, 0.0, 0.0),
    "perpendicular": (0.0, 1.0, 0.0),
    "diagonal": (math.sqrt(0.5), math.sqrt(0.5), 0.0),
}
THESIS_ANGLES_DEG = (30.0, 60.0, 90.0)
THESIS_DEPTH_MM = 0.5
THESIS_FEED_MM_S = 3.0
THESIS_RPM = 60000.0


@dataclass(frozen=True)
class CuttingCase:
    """One steady-cutting case on the flat workpiece (bone in z < 0)."""

    orientation: str
    angle_deg: float
    radius_mm: float = 2.0
    depth_mm: float = THESIS_DEPTH_MM
    feed_mm_s: float = THESIS_FEED_MM_S
    rpm: float = THESIS_RPM

    def __post_init__(self) -> None:
        if self.orientation not in ORIENTATIONS:
            raise ValueError(
                f"orientation must be one of {sorted(ORIENTATIONS)}, got {self.orientation!r}"
            )
        if not 0.0 < self.angle_deg <= 90.0:
            raise ValueError(f"angle_deg must be in (0, 90], got {self.angle_deg}")
        if not 0.0 < self.depth_mm <= 2.0 * self.radius_mm:
            raise ValueError(
                f"depth_mm must be in (0, 2R] = (0, {2.0 * self.radius_mm}], got {self.depth_mm}"
            )

    @property
    def centre_mm(self) -> np.ndarray:
        return np.array([0.0, 0.0, self.radius_mm - self.depth_mm])

    @property
    def axis(self) -> np.ndarray:
        alpha = math.radians(self.angle_deg)
        return np.array([-math.cos(alpha), 0.0, math.sin(alpha)])

    @property
    def feed_direction(self) -> np.ndarray:
        return np.array(ORIENTATIONS[self.orientation])

    @property
    def feed_velocity_mm_s(self) -> np.ndarray:
        return self.feed_mm_s * self.feed_direction


def thesis_cases(
    angles_deg: Iterable[float] = THESIS_ANGLES_DEG,
    orientations: Iterable[str] = tuple(ORIENTATIONS),
    **geometry: float,
) -> Iterator[CuttingCase]:
    """Cases orientation-major, angle-minor (the thesis's nine by default)."""
    angles = tuple(angles_deg)
    for orientation in orientations:
        for angle in angles:
            yield CuttingCase(orientation, float(angle), **geometry)
