"""Phase-continuous sine synthesizer for the vibration cue, with a perceptual mode.

Each block ramps amplitude, frequency and AM depth linearly from the previous block's values
to the new target, and the phase carries over across blocks and frequency changes, so a
parameter change never clicks. A stale stream (see :meth:`Oscillator.render`) ramps to zero
within one block and stays there until a new target arrives.

Perceptual mode (``synth.Perceptual``): skin is most sensitive near 250 Hz and barely feels
sinusoids above ~800 Hz, yet a 60 000 rpm burr vibrates at 1 kHz (several kHz for a fluted
burr). Two remedies above ``corner_hz``:

- ``"am"``: keep the carrier and amplitude-modulate it with a raised cosine at ``am_hz``
  (250 Hz by default): Lamoré, Muijser & Keemink (JASA 1986) found 1–2 kHz sinusoids that
  are otherwise imperceptible become perceptible when amplitude-modulated near 200 Hz. The
  spectrum keeps the spindle's frequency (f ± am_hz sidebands), the envelope is felt.
- ``"clamp"``: replace the carrier by ``corner_hz``; loses the pitch, keeps the buzz.
- ``"off"``: the carrier as sent (the default), e.g. for a research rig that measures it.

The AM depth ramps in and out over a block as the frequency crosses the corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

PERCEPTUAL_MODES = ("off", "am", "clamp")
#: Highest carrier as a fraction of the sample rate: keeps ≥ 2.2 samples per period, so the
#: tone never aliases.
MAX_CARRIER_FRACTION = 0.45


@dataclass(frozen=True)
class Perceptual:
    """How frequencies above the skin's range are rendered.

    Attributes:
        mode: ``"off"``, ``"am"`` or ``"clamp"`` (module docstring).
        corner_hz: frequencies above it get the treatment, Hz.
        am_hz: AM rate for ``"am"``, Hz.
    """

    mode: str = "off"
    corner_hz: float = 800.0
    am_hz: float = 250.0

    def __post_init__(self) -> None:
        if self.mode not in PERCEPTUAL_MODES:
            raise ValueError(f"perceptual mode must be one of {PERCEPTUAL_MODES}, "
                             f"got {self.mode!r}")
        for name in ("corner_hz", "am_hz"):
            value = getattr(self, name)
            if not math.isfinite(value) or value <= 0.0:
                raise ValueError(f"{name} must be finite and > 0, got {value}")

    @classmethod
    def of(cls, value: Perceptual | str | None) -> Perceptual:
        """A Perceptual from itself, a mode name (``"am"``: what a device spec's
        ``perceptual=am`` option gives) or None (off)."""
        if value is None:
            return cls()
        if isinstance(value, str):
            return cls(value)
        if not isinstance(value, cls):
            raise ValueError(f"perceptual must be one of {PERCEPTUAL_MODES}, got {value!r}")
        return value

    def carrier(self, frequency_hz: float) -> tuple[float, float]:
        """(carrier frequency Hz, AM depth 0..1) for the requested frequency."""
        if frequency_hz <= self.corner_hz or self.mode == "off":
            return frequency_hz, 0.0
        if self.mode == "clamp":
            return self.corner_hz, 0.0
        return frequency_hz, 1.0


@njit(cache=True, nogil=True)
def fill_block(out, rate_hz, phase, f0_hz, f1_hz, a0, a1, am_phase, am_hz, m0, m1):
    """Fill ``out`` ((n,) float32) with ``a·env·sin(2π·phase)``, ramping linearly from
    (f0_hz, a0, m0) at the first sample to (f1_hz, a1, m1) at the last.

    ``phase`` and ``am_phase`` are in cycles [0, 1); ``m`` is the AM depth (envelope
    ``1 − m·(0.5 + 0.5·cos 2π·am_phase)``, so m = 1 is a full raised-cosine modulation that
    starts at zero). Returns the phases for the next block's first sample.
    """
    n = out.shape[0]
    if n == 0:
        return phase, am_phase
    two_pi = 2.0 * np.pi
    am_step = am_hz / rate_hz
    denom = max(n - 1, 1)
    for i in range(n):
        t = i / denom
        f = f0_hz + (f1_hz - f0_hz) * t
        a = a0 + (a1 - a0) * t
        m = m0 + (m1 - m0) * t
        env = 1.0 - m * (0.5 + 0.5 * np.cos(two_pi * am_phase))
        out[i] = a * env * np.sin(two_pi * phase)
        phase += f / rate_hz
        phase -= np.floor(phase)
        am_phase += am_step
        am_phase -= np.floor(am_phase)
    return phase, am_phase


class Oscillator:
    """The synthesizer's state between blocks. Not thread-safe by itself: one thread renders;
    another may call :meth:`set_target` (it swaps one tuple, atomic under the GIL).

    Args:
        rate_hz: sample rate, Hz.
        perceptual: the perceptual mode (:class:`Perceptual`).
    """

    def __init__(self, rate_hz: float = 48_000.0,
                 perceptual: Perceptual | None = None) -> None:
        if not math.isfinite(rate_hz) or rate_hz <= 0.0:
            raise ValueError(f"rate_hz must be finite and > 0, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.perceptual = perceptual or Perceptual()
        self.max_carrier_hz = MAX_CARRIER_FRACTION * self.rate_hz
        self._target = (0.0, 0.0)  # (level 0..1, frequency Hz) as requested
        self._phase = 0.0
        self._am_phase = 0.0
        self._level = 0.0
        self._carrier_hz = 0.0
        self._depth = 0.0
        self._stale = False

    def set_target(self, level: float, frequency_hz: float) -> None:
        """New target: ``level`` 0..1 of full scale, ``frequency_hz`` ≥ 0 (0: silence).
        Clears a stale state."""
        if not (math.isfinite(level) and math.isfinite(frequency_hz)) or frequency_hz < 0.0:
            raise ValueError(f"bad target level={level} frequency_hz={frequency_hz}")
        self._target = (min(max(level, 0.0), 1.0), frequency_hz)
        self._stale = False

    @property
    def level(self) -> float:
        """The level the last block ended at."""
        return self._level

    @property
    def silent(self) -> bool:
        """The last block ended at zero and no non-zero target is pending."""
        return self._level == 0.0 and (self._stale or self._target[0] == 0.0
                                       or self._target[1] == 0.0)

    def render(self, out: np.ndarray, stale: bool = False) -> bool:
        """Fill ``out`` ((n,) float32, contiguous) with the next block.

        ``stale``: the parameter stream stopped; ramp to zero within this block and stay zero
        until the next :meth:`set_target`.

        Returns:
            True if this block is where a sounding output starts falling silent for being
            stale (the watchdog fired), False otherwise.
        """
        fired = stale and not self._stale and not self.silent
        if stale:
            self._stale = True
        level, frequency_hz = self._target
        if self._stale or frequency_hz <= 0.0:
            level = 0.0
        carrier_hz, depth = self.perceptual.carrier(frequency_hz)
        carrier_hz = min(carrier_hz, self.max_carrier_hz)
        if level == 0.0 and frequency_hz <= 0.0:
            carrier_hz, depth = self._carrier_hz, self._depth  # fade out at the old pitch
        if self._level == 0.0:
            # Starting from silence: no chirp up from the old pitch, no AM ramp.
            self._carrier_hz, self._depth = carrier_hz, depth
        self._phase, self._am_phase = fill_block(
            out, self.rate_hz, self._phase, self._carrier_hz, carrier_hz, self._level, level,
            self._am_phase, self.perceptual.am_hz, self._depth, depth)
        self._level, self._carrier_hz, self._depth = level, carrier_hz, depth
        return fired

    def block(self, n: int, stale: bool = False) -> np.ndarray:
        """The next ``n`` samples as a new (n,) float32 array."""
        out = np.empty(n, dtype=np.float32)
        self.render(out, stale)
        return out
