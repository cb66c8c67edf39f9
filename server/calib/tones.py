"""A dynamometer signal's spindle tone (thesis §2.4, §2.5.2): the checks every analysis
makes of its input, the least-squares sinusoid fit at the spindle frequency (unbiased), the
thesis's peak method (biased at 3 samples per cycle) and the dominant frequency by FFT.

Problems with the data raise :class:`AnalysisError` (a ``ValueError``) saying what is wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft, optimize
from scipy import signal as sps

#: Without an rpm, the spindle is the strongest line above this (hand motion lives below).
MIN_SPINDLE_HZ = 20.0
#: Default relative search band for the spindle frequency (spindles slow under load).
SEARCH_FRACTION = 0.02


class AnalysisError(ValueError):
    """A recording (or signal) that cannot be analysed; the message says why."""


# --- validation ------------------------------------------------------------------------------


def as_signal(x: np.ndarray, name: str = "x", min_len: int = 4) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise AnalysisError(f"{name} is not numeric") from None
    if arr.ndim != 1:
        raise AnalysisError(f"{name} must be 1-D, got shape {arr.shape}")
    if len(arr) < min_len:
        raise AnalysisError(f"{name} has {len(arr)} samples; at least {min_len} are needed")
    if not np.isfinite(arr).all():
        raise AnalysisError(f"{name} holds {int((~np.isfinite(arr)).sum())} NaN/inf value(s)")
    return arr


def as_force(force_N: np.ndarray) -> np.ndarray:
    try:
        arr = np.asarray(force_N, dtype=np.float64)
    except (TypeError, ValueError):
        raise AnalysisError("force_N is not numeric") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise AnalysisError(f"force_N must have shape (n, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise AnalysisError(f"force_N holds {int((~np.isfinite(arr)).sum())} NaN/inf value(s)")
    return arr


def positive(value: float, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise AnalysisError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out) or out <= 0.0:
        raise AnalysisError(f"{name} must be finite and > 0, got {out}")
    return out


def check_nyquist(sample_rate_hz: float, spindle_hz: float, what: str = "") -> None:
    if sample_rate_hz <= 2.0 * spindle_hz:
        raise AnalysisError(
            f"sample rate {sample_rate_hz:g} Hz is not above twice the spindle frequency "
            f"{spindle_hz:g} Hz{what}: the spindle tone aliases; record at more than "
            f"{2.0 * spindle_hz:g} Hz")


# --- sinusoid fit ----------------------------------------------------------------------------


@dataclass(frozen=True)
class SineFit:
    """x ≈ offset_N + amplitude_N·cos(2π·frequency_hz·t + phase_rad), t from x's first sample."""

    amplitude_N: float
    phase_rad: float
    offset_N: float
    frequency_hz: float
    rms_residual_N: float


def _design(n: int, sample_rate_hz: float, frequency_hz: float) -> np.ndarray:
    """(n, 3): 1, cos(2πft), sin(2πft)."""
    phase = (2.0 * np.pi * frequency_hz / sample_rate_hz) * np.arange(n)
    return np.column_stack([np.ones(n), np.cos(phase), np.sin(phase)])


def _lstsq(x: np.ndarray, sample_rate_hz: float, frequency_hz: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients (3, k) of offset, cos, sin and the residual sum of squares (k,) of x (n, k)."""
    design = _design(len(x), sample_rate_hz, frequency_hz)
    coef, *_ = np.linalg.lstsq(design, x, rcond=None)
    resid = x - design @ coef
    return coef, np.einsum("ij,ij->j", resid, resid)


def refine_frequency(x: np.ndarray, sample_rate_hz: float, frequency_hz: float,
                      search_fraction: float) -> float:
    """The least-squares frequency of one sinusoid shared by the columns of x (n, k), within
    ±search_fraction of frequency_hz: the RSS is multimodal (lobes 1/duration wide), so a
    zero-padded periodogram picks the lobe and a bounded scalar search polishes it."""
    nyquist = sample_rate_hz / 2.0
    lo = max(frequency_hz * (1.0 - search_fraction), 1e-9 * frequency_hz)
    hi = min(frequency_hz * (1.0 + search_fraction), nyquist * (1.0 - 1e-9))
    if hi - lo <= 0.0:
        return frequency_hz
    n = len(x)
    n_fft = fft.next_fast_len(4 * n, real=True)
    power = np.sum(np.abs(fft.rfft(x - x.mean(axis=0), n_fft, axis=0)) ** 2, axis=1)
    freqs = fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    band = np.flatnonzero((freqs >= lo) & (freqs <= hi))
    if len(band):
        peak = freqs[band[np.argmax(power[band])]]
        step = sample_rate_hz / n_fft
        lo, hi = max(lo, peak - step), min(hi, peak + step)

    # Searched in u ∈ [−1, 1] across the bracket: Brent's tolerance is relative to |u|, so
    # this resolves the frequency far below a µHz instead of √ε·f (15 µHz at 1 kHz).
    centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0

    def rss(u: float) -> float:
        return float(_lstsq(x, sample_rate_hz, centre + half * u)[1].sum())

    result = optimize.minimize_scalar(rss, bounds=(-1.0, 1.0), method="bounded",
                                      options={"xatol": 1e-9})
    return float(centre + half * result.x)


def sine_fits(x: np.ndarray, sample_rate_hz: float, frequency_hz: float
               ) -> tuple[list[SineFit], np.ndarray]:
    """Per column of x (n, k) at one frequency: the fits and the tone alone (n, k)."""
    coef, rss = _lstsq(x, sample_rate_hz, frequency_hz)
    design = _design(len(x), sample_rate_hz, frequency_hz)
    tone = design[:, 1:] @ coef[1:]
    fits = [SineFit(amplitude_N=float(math.hypot(coef[1, j], coef[2, j])),
                    phase_rad=float(math.atan2(-coef[2, j], coef[1, j])),
                    offset_N=float(coef[0, j]), frequency_hz=float(frequency_hz),
                    rms_residual_N=float(math.sqrt(max(rss[j], 0.0) / len(x))))
            for j in range(x.shape[1])]
    return fits, tone


def sine_fit(x: np.ndarray, sample_rate_hz: float, frequency_hz: float, *, refine: bool = True,
             search_fraction: float = SEARCH_FRACTION) -> SineFit:
    """Least squares x ≈ offset + a·cos(2πft) + b·sin(2πft) over x (n,).

    Unbiased for the amplitude whatever the samples per cycle (unlike peak-picking). With
    ``refine`` the frequency is the least-squares (maximum-likelihood, for white noise) one
    within ±``search_fraction`` of ``frequency_hz``: spindles slow under load.

    Raises:
        AnalysisError: x not 1-D finite with ≥ 4 samples, or frequency not in (0, rate/2).
    """
    x = as_signal(x)
    sample_rate_hz = positive(sample_rate_hz, "sample_rate_hz")
    frequency_hz = positive(frequency_hz, "frequency_hz")
    if frequency_hz >= sample_rate_hz / 2.0:
        raise AnalysisError(f"frequency {frequency_hz:g} Hz is not below the Nyquist frequency "
                            f"{sample_rate_hz / 2.0:g} Hz: it aliases")
    if not 0.0 <= search_fraction < 0.5:
        raise AnalysisError(f"search_fraction must be in [0, 0.5), got {search_fraction}")
    column = x[:, None]
    if refine and search_fraction > 0.0:
        frequency_hz = refine_frequency(column, sample_rate_hz, frequency_hz, search_fraction)
    return sine_fits(column, sample_rate_hz, frequency_hz)[0][0]


# --- the thesis's peak method and the FFT ----------------------------------------------------


def peak_amplitude(x: np.ndarray) -> float:
    """The thesis's vibration amplitude of x (n,): (mean of the upper peaks − mean of the lower
    peaks) / 2 of the mean-removed signal. Upper peaks are local maxima above the mean, lower
    peaks local minima below it (``scipy.signal.find_peaks``). 0 if there are none.

    Biased when a cycle has few samples: at 3 per cycle the sampled extremes fall short of the
    crest (0.75–0.87 of the amplitude, by phase), and noise adds to them.
    """
    y = as_signal(x, min_len=3)
    y = y - y.mean()
    upper, _ = sps.find_peaks(y, height=0.0)
    lower, _ = sps.find_peaks(-y, height=0.0)
    if len(upper) == 0 or len(lower) == 0:
        return 0.0
    return float((y[upper].mean() - y[lower].mean()) / 2.0)


def dominant_frequency(x: np.ndarray, sample_rate_hz: float, *, min_hz: float = 0.0) -> float:
    """The strongest spectral line of x (n,) or (n, k) (power summed over columns), Hz.

    Linear trend removed, Hann window, zero-padded FFT, the peak refined below one bin by a
    parabola through the log power (nearly exact for a Hann window's main lobe). DC and the
    window's main lobe around it (two bins) are ignored, and so is everything below
    ``min_hz``.

    Raises:
        AnalysisError: too short, no line above ``min_hz``, or a signal without oscillation.
    """
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise AnalysisError(f"x must be (n,) or (n, k), got shape {arr.shape}")
    n = len(arr)
    if n < 8:
        raise AnalysisError(f"x has {n} samples; at least 8 are needed for an FFT")
    if not np.isfinite(arr).all():
        raise AnalysisError("x holds NaN/inf values")
    sample_rate_hz = positive(sample_rate_hz, "sample_rate_hz")
    window = sps.get_window("hann", n)[:, None]
    n_fft = fft.next_fast_len(4 * n, real=True)
    spectrum = fft.rfft(sps.detrend(arr, axis=0) * window, n_fft, axis=0)
    power = np.sum(np.abs(spectrum) ** 2, axis=1)
    freqs = fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    first = int(np.searchsorted(freqs, max(float(min_hz), 2.0 * sample_rate_hz / n)))
    if first >= len(freqs) - 1:
        raise AnalysisError(f"no frequencies above {max(min_hz, 2.0 * sample_rate_hz / n):g} Hz "
                            f"below Nyquist in {n} samples")
    k = first + int(np.argmax(power[first:]))
    if power[k] <= 0.0:
        raise AnalysisError("the signal has no oscillation (flat spectrum)")
    step = freqs[1]
    if first < k < len(power) - 1 and power[k - 1] > 0.0 and power[k + 1] > 0.0:
        left, mid, right = np.log(power[k - 1 : k + 2])
        curvature = left - 2.0 * mid + right
        if curvature < 0.0:
            return float(freqs[k] + 0.5 * (left - right) / curvature * step)
    return float(freqs[k])
