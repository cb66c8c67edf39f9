"""Discretization of the spherical burr in its tool frame (latitude/longitude about the spin axis).

Element (j, k) covers θ ∈ [j·dθ, (j+1)·dθ], φ ∈ [k·dφ, (k+1)·dφ], where θ is measured from the
tool axis a (toward the handle) and φ around it. Its centre sits at the midpoint. The model's
cancelled weight dA/|v_t| = R·dθ·dφ/ω is the same for every element, so nothing is ever divided
by the vanishing spin speed near the poles (model.md, "the trap at the poles").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Default resolution: measured by ``burrforce bench model`` (benchmarks/model.md) to stay well
#: inside 0.5 % of the converged reference on the thesis's nine cases.
DEFAULT_N_THETA = 24
#: Elements the bone surface cuts through are split into REFINE×REFINE sub-elements.
DEFAULT_REFINE = 3


@dataclass(frozen=True, eq=False)
class BurrGrid:
    """Latitude/longitude tables for one resolution. Immutable; shared between evaluations.

    Attributes:
        n_theta: number of latitude bands (θ from 0 at the handle-side pole to π at the tip).
        n_phi: number of longitude sectors (2·n_theta by default: near-square elements at the
            equator; a multiple of 4 keeps the quarter-turn symmetry about the axis).
        cos_theta, sin_theta: shape (n_theta,), at the band midpoints.
        cos_phi, sin_phi: shape (n_phi,), at the sector midpoints.
        d_theta, d_phi: element extents, rad.
        refine: an element the bone surface crosses is split into refine×refine sub-elements.
        cos_sub_t, sin_sub_t: shape (refine,), θ-offsets of the sub-element centres.
        cos_sub_p, sin_sub_p: shape (refine,), φ-offsets of the sub-element centres.
        cos_theta_v, sin_theta_v: shape (n_theta + 1,), at the band edges (element corners).
        cos_phi_v, sin_phi_v: shape (n_phi,), at the sector edges (element corners).
    """

    n_theta: int
    n_phi: int
    cos_theta: np.ndarray
    sin_theta: np.ndarray
    cos_phi: np.ndarray
    sin_phi: np.ndarray
    d_theta: float
    d_phi: float
    refine: int
    cos_sub_t: np.ndarray
    sin_sub_t: np.ndarray
    cos_sub_p: np.ndarray
    sin_sub_p: np.ndarray
    cos_theta_v: np.ndarray
    sin_theta_v: np.ndarray
    cos_phi_v: np.ndarray
    sin_phi_v: np.ndarray

    @property
    def n_elements(self) -> int:
        return self.n_theta * self.n_phi

    @classmethod
    def build(
        cls, n_theta: int = DEFAULT_N_THETA, n_phi: int | None = None,
        refine: int = DEFAULT_REFINE,
    ) -> BurrGrid:
        """Tables for ``n_theta`` bands, ``n_phi`` sectors (default 2·n_theta) and boundary
        elements split ``refine``×``refine``."""
        if n_phi is None:
            n_phi = 2 * n_theta
        for name, n in (("n_theta", n_theta), ("n_phi", n_phi), ("refine", refine)):
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
                raise TypeError(f"{name} must be an integer, got {type(n).__name__}")
        if not 2 <= n_theta <= 4096 or not 4 <= n_phi <= 8192 or not 1 <= refine <= 16:
            raise ValueError(
                f"burr resolution out of range: n_theta={n_theta} (2..4096), "
                f"n_phi={n_phi} (4..8192), refine={refine} (1..16)"
            )
        d_theta = math.pi / n_theta
        d_phi = 2.0 * math.pi / n_phi
        theta = (np.arange(n_theta) + 0.5) * d_theta
        phi = (np.arange(n_phi) + 0.5) * d_phi
        sub = ((np.arange(refine) + 0.5) / refine - 0.5)
        main = _tables(theta, phi)
        subs = _tables(sub * d_theta, sub * d_phi)
        corners = _tables(np.arange(n_theta + 1) * d_theta, np.arange(n_phi) * d_phi)
        return cls(int(n_theta), int(n_phi), *main, d_theta, d_phi, int(refine), *subs,
                   *corners)

    @property
    def key(self) -> tuple[int, int, int]:
        return self.n_theta, self.n_phi, self.refine

    @classmethod
    def from_element_count(cls, n_elements: int) -> BurrGrid:
        """The grid with n_phi = 2·n_theta whose element count is closest to ``n_elements``."""
        if n_elements < 8:
            raise ValueError(f"need at least 8 burr elements, got {n_elements}")
        n_theta = max(2, round(math.sqrt(n_elements / 2.0)))
        return cls.build(n_theta)


def _tables(theta: np.ndarray, phi: np.ndarray) -> list[np.ndarray]:
    tables = [np.ascontiguousarray(t, dtype=np.float64)
              for t in (np.cos(theta), np.sin(theta), np.cos(phi), np.sin(phi))]
    for t in tables:
        t.flags.writeable = False
    return tables
