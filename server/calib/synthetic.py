"""Recordings of known truth: the thesis's protocol (free spin, burring, free spin) simulated.

force(t) = offset + drift·t + mean·envelope(t) + tone(t) + noise, per axis, where the envelope
is 0 while spinning free, ramps linearly to 1 over ``ramp_s``, holds for ``burring_s`` and ramps
back; the tone is amp·(1 + (gain − 1)·envelope)·cos(2π·spindle_hz·t + phase) and the noise
white Gaussian. Half-height of the envelope, the truth for segment boundaries, is at
``free_s + ramp_s/2`` and ``free_s + 1.5·ramp_s + burring_s``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from .recording import Recording


def _vector(value: ArrayLike, name: str) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (3,)).copy()
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


def burring_envelope(t_s: np.ndarray, free_s: float, burring_s: float, ramp_s: float
                     ) -> np.ndarray:
    """(n,) 0 → linear ramp → 1 → ramp → 0 at times t_s."""
    t = np.asarray(t_s, dtype=np.float64)
    start, stop = free_s, free_s + 2.0 * ramp_s + burring_s
    if ramp_s > 0.0:
        up = (t - start) / ramp_s
        down = (stop - t) / ramp_s
        return np.clip(np.minimum(up, down), 0.0, 1.0)
    return ((t >= start) & (t < stop)).astype(np.float64)


def synthetic_recording(
    mean_force_N: ArrayLike, *, sample_rate_hz: float = 3000.0, spindle_hz: float = 1000.0,
    tone_amplitude_N: ArrayLike = (0.3, 0.3, 0.3), tone_phase_rad: ArrayLike | None = None,
    noise_N: float = 0.0, drift_N_s: ArrayLike = (0.0, 0.0, 0.0),
    offset_N: ArrayLike = (0.0, 0.0, 0.0), free_s: float = 1.0, burring_s: float = 2.0,
    ramp_s: float = 0.1, burring_tone_gain: float = 1.0, seed: int | None = None,
    metadata: dict | None = None,
) -> Recording:
    """A recording of known truth (see the module doc). Vectors are (3,) or scalars (all axes).

    ``tone_phase_rad`` per axis; random (from ``seed``) if None. ``seed`` also draws the noise.

    Raises:
        ValueError: a non-finite or negative duration, rate, noise or gain.
    """
    for name, value in (("sample_rate_hz", sample_rate_hz), ("spindle_hz", spindle_hz)):
        if not math.isfinite(value) or value <= 0.0:
            raise ValueError(f"{name} must be finite and > 0, got {value}")
    for name, value in (("noise_N", noise_N), ("free_s", free_s), ("burring_s", burring_s),
                        ("ramp_s", ramp_s), ("burring_tone_gain", burring_tone_gain)):
        if not math.isfinite(value) or value < 0.0:
            raise ValueError(f"{name} must be finite and ≥ 0, got {value}")
    mean = _vector(mean_force_N, "mean_force_N")
    amp = _vector(tone_amplitude_N, "tone_amplitude_N")
    drift = _vector(drift_N_s, "drift_N_s")
    offset = _vector(offset_N, "offset_N")
    rng = np.random.default_rng(seed)
    phase = (rng.uniform(0.0, 2.0 * np.pi, 3) if tone_phase_rad is None
             else _vector(tone_phase_rad, "tone_phase_rad"))

    n = round((2.0 * free_s + 2.0 * ramp_s + burring_s) * sample_rate_hz)
    t = np.arange(n) / sample_rate_hz
    envelope = burring_envelope(t, free_s, burring_s, ramp_s)[:, None]
    gain = 1.0 + (burring_tone_gain - 1.0) * envelope
    tone = amp * gain * np.cos(2.0 * np.pi * spindle_hz * t[:, None] + phase)
    force = offset + drift * t[:, None] + mean * envelope + tone
    if noise_N > 0.0:
        force = force + noise_N * rng.standard_normal((n, 3))
    source = (f"synthetic: mean {np.round(mean, 6).tolist()} N, {spindle_hz:g} Hz tone at "
              f"{sample_rate_hz:g} Hz, noise {noise_N:g} N")
    return Recording(force, sample_rate_hz, source, dict(metadata or {}))
