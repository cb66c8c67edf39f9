"""Vibration parameters (model.md, thesis §2.5.2 and §3.3).

Humans do not perceive the direction of a ~1 kHz vibration, so it is a scalar amplitude at the
spindle frequency; the client or a separate actuator synthesizes the waveform.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class VibrationParams:
    """Attributes:
    fd_N: amplitude while spinning free, N. Measure it per drill (the thesis's burring /
        non-burring ratio ≈ 1 means this term dominates). The default 0.5 N is illustrative
        only, not a measured value.
    g: burring gain ≥ 0 on |F_r|; 0 is the thesis's finding.
    harmonic: frequency multiple of the rotation rate (1 for grinding burrs; the number of
        flutes for a fluted burr).
    """

    fd_N: float = 0.5
    g: float = 0.0
    harmonic: float = 1.0

    def __post_init__(self) -> None:
        for name in ("fd_N", "g", "harmonic"):
            value = getattr(self, name)
            if not math.isfinite(value) or value < 0.0:
                raise ValueError(f"{name} must be finite and ≥ 0, got {value}")
        if self.harmonic == 0.0:
            raise ValueError("harmonic must be > 0")


def vibration(
    rpm: float, resistive_force_N: float, spindle_on: bool, params: VibrationParams
) -> tuple[float, float]:
    """(amplitude_N, frequency_Hz) of the vibration to render.

    amplitude = sqrt(Fd² + (g·|F_r|)²), frequency = |rpm|/60 × harmonic; both zero when the
    spindle is off or not turning. ``resistive_force_N`` is |F_r|, N.
    """
    if not spindle_on or rpm == 0.0 or not math.isfinite(rpm):
        return 0.0, 0.0
    burring = params.g * abs(resistive_force_N)
    return math.hypot(params.fd_N, burring), abs(rpm) / 60.0 * params.harmonic


#: The most flutes a fluted burr may have.
MAX_FLUTES = 64


def flute_harmonic(n_flutes: int) -> float:
    """The vibration harmonic of a fluted burr: each of its ``n_flutes`` edges strikes the bone
    once a turn, so the dominant frequency is the tooth-passing rate n_flutes × |rpm|/60 (for
    ``VibrationParams.harmonic``). Abrasive burrs keep the default harmonic 1."""
    if isinstance(n_flutes, bool) or not isinstance(n_flutes, int) or not (
            1 <= n_flutes <= MAX_FLUTES):
        raise ValueError(f"n_flutes must be an integer in [1, {MAX_FLUTES}], got {n_flutes!r}")
    return float(n_flutes)
