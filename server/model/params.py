"""Cutting parameters of one burr and one bone material (units in the names)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

Spin = Literal["forward", "reverse"]

#: The thesis's calibrated specific cutting energy for its synthetic cortical bone, N/mm².
THESIS_US_N_MM2 = 805.1
#: The thesis's normal/tangential force ratio.
THESIS_K = 1.3


@dataclass(frozen=True)
class CuttingParams:
    """Parameters of the specific-cutting-energy model (model.md).

    Attributes:
        us_n_mm2: specific cutting energy Us, N/mm² (= N·mm of work per mm³ removed).
        k: normal/tangential force ratio K, dimensionless, ≥ 0.
        radius_mm: burr radius R (a "4 mm burr" is a diameter: R = 2 mm).
        spin: "forward" (clockwise seen from the handle looking at the tip, Ω = −ω·a)
            or "reverse" (Ω = +ω·a).
        min_cutting_rpm: below this spindle speed the burr does not cut; the bone is a rigid
            obstacle and the model reports contact instead. As ω → 0 the cutting force grows
            like 1/ω, so this must stay well above zero.
    """

    us_n_mm2: float = THESIS_US_N_MM2
    k: float = THESIS_K
    radius_mm: float = 2.0
    spin: Spin = "forward"
    min_cutting_rpm: float = 5000.0

    def __post_init__(self) -> None:
        _check_finite_range("us_n_mm2", self.us_n_mm2, 0.0, 1e7)
        _check_finite_range("k", self.k, 0.0, 100.0)
        _check_finite_range("radius_mm", self.radius_mm, 1e-3, 100.0, low_inclusive=False)
        _check_finite_range("min_cutting_rpm", self.min_cutting_rpm, 1.0, 1e7)
        if self.spin not in ("forward", "reverse"):
            raise ValueError(f"spin must be 'forward' or 'reverse', got {self.spin!r}")

    @property
    def spin_sign(self) -> float:
        """+1 for reverse (Ω = +ω·a), −1 for forward (Ω = −ω·a)."""
        return 1.0 if self.spin == "reverse" else -1.0

    def with_(self, **changes: object) -> CuttingParams:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]


def _check_finite_range(
    name: str, value: float, low: float, high: float, *, low_inclusive: bool = True
) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{name} must be a number, got {type(value).__name__}")
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    too_low = value < low if low_inclusive else value <= low
    if too_low or value > high:
        bracket = "[" if low_inclusive else "("
        raise ValueError(f"{name} must be in {bracket}{low}, {high}], got {value}")
