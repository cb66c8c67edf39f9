"""The coupled output's transition from rigid contact to cutting across a band of spindle
speed above the minimum cutting speed (``coupling.coupled_finish`` blends by this weight).

Below ``min_rpm`` the burr is a rigid obstacle; from ``min_rpm`` to ``min_rpm + band_rpm`` the
weight s of the cut rises as a smooth step (C¹: no step in the force, nor in its slope, as the
spindle spins up or down); above, the burr only cuts.
"""

from __future__ import annotations


def cut_weight(rpm_abs: float, min_rpm: float, band_rpm: float) -> float:
    """s ∈ [0, 1], the cut's share of the bone's answer at spindle speed ``rpm_abs`` (|rpm|):
    0 below ``min_rpm``, 1 from ``min_rpm + band_rpm`` on, 3u² − 2u³ in between
    (u = (rpm_abs − min_rpm)/band_rpm). Plain Python: the session calls it once per tick,
    cheaper than a kernel dispatch."""
    if rpm_abs < min_rpm:
        return 0.0
    if rpm_abs >= min_rpm + band_rpm:
        return 1.0
    u = (rpm_abs - min_rpm) / band_rpm
    return u * u * (3.0 - 2.0 * u)
