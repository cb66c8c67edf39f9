"""Cutting parameters of one burr and one bone material (units in the names)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

from .shapes import Abrasive, Burr, Sphere

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
        cutting_band: the coupled output's transition from rigid contact to cutting spans
            the spindle speeds from ``min_cutting_rpm`` to ``(1 + cutting_band)`` times it
            (``haptics.transition``), dimensionless, > 0.
        burr: the burr's shape and cutter (``shapes.Burr``) when it is not a round abrasive
            burr; None is a sphere of ``radius_mm`` with grit (a round abrasive ``burr`` is
            stored that way). With another shape, ``radius_mm`` is its largest radius.
    """

    us_n_mm2: float = THESIS_US_N_MM2
    k: float = THESIS_K
    radius_mm: float = 2.0
    spin: Spin = "forward"
    min_cutting_rpm: float = 5000.0
    burr: Burr | None = None
    cutting_band: float = 0.2

    def __post_init__(self) -> None:
        if self.burr is not None:
            if not isinstance(self.burr, Burr):
                raise ValueError(f"burr must be a shapes.Burr, got {type(self.burr).__name__}")
            # One spelling per burr: a round abrasive burr is the sphere of radius_mm.
            object.__setattr__(self, "radius_mm", float(self.burr.shape.max_radius_mm))
            if isinstance(self.burr.shape, Sphere) and isinstance(self.burr.cutter, Abrasive):
                object.__setattr__(self, "burr", None)
        _check_finite_range("us_n_mm2", self.us_n_mm2, 0.0, 1e7)
        _check_finite_range("k", self.k, 0.0, 100.0)
        _check_finite_range("radius_mm", self.radius_mm, 1e-3, 100.0, low_inclusive=False)
        _check_finite_range("min_cutting_rpm", self.min_cutting_rpm, 1.0, 1e7)
        _check_finite_range("cutting_band", self.cutting_band, 0.0, 10.0, low_inclusive=False)
        if self.spin not in ("forward", "reverse"):
            raise ValueError(f"spin must be 'forward' or 'reverse', got {self.spin!r}")

    @property
    def spin_sign(self) -> float:
        """+1 for reverse (Ω = +ω·a), −1 for forward (Ω = −ω·a)."""
        return 1.0 if self.spin == "reverse" else -1.0

    @property
    def shape(self) -> Burr:
        """The burr, spelled out (a round abrasive one when ``burr`` is None)."""
        return self.burr if self.burr is not None else Burr(Sphere(self.radius_mm))

    def with_(self, **changes: object) -> CuttingParams:
        """A copy with some fields changed (validated again)."""
        return replace(self, **changes)  # type: ignore[arg-type]

    def to_dict(self) -> dict:
        """JSON-able fields (``burr`` as ``Burr.to_dict``); ``from_dict`` reads it back."""
        return {"us_n_mm2": self.us_n_mm2, "k": self.k, "radius_mm": self.radius_mm,
                "spin": self.spin, "min_cutting_rpm": self.min_cutting_rpm,
                "cutting_band": self.cutting_band,
                "burr": None if self.burr is None else self.burr.to_dict()}

    @classmethod
    def from_dict(cls, data: dict) -> CuttingParams:
        fields = dict(data)
        if fields.get("burr") is not None:
            fields["burr"] = Burr.from_dict(fields["burr"])
        return cls(**fields)


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
