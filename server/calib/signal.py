"""Mean force and vibration of a dynamometer recording (thesis §2.4, §2.5.2; model.md).

A recording follows the thesis's protocol: the drill spins free (non-burring: mean ≈ 0 plus the
spindle tone), cuts (burring: the mean shifts by the cutting force, the tone stays), and spins
free again. :func:`find_segments` finds the burring run and fits the dynamometer's drift on the
free-spinning samples; :func:`analyse` measures, over the burring window:

- the mean force (baseline removed), jointly fitted with the spindle sinusoid so the tone
  cannot bias it, and an honest standard error (batch means over blocks of whole periods);
- the vibration amplitude per axis two ways: the thesis's peak method (:func:`peak_amplitude`,
  biased at 3 samples per cycle) and a least-squares sinusoid fit (:func:`sine_fit`,
  unbiased), their resultants and the burring / non-burring ratio (the thesis found ≈ 1);
- the dominant frequency by FFT (:func:`dominant_frequency`).

Problems with the data raise :class:`AnalysisError` (a ``ValueError``) saying what is wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import fft, ndimage, optimize
from scipy import signal as sps
from skimage.filters import threshold_otsu

from .recording import Recording

#: Without an rpm, the spindle is the strongest line above this (hand motion lives below).
MIN_SPINDLE_HZ = 20.0
#: The moving average spans at least this long (and whole spindle periods).
SMOOTHING_MIN_S = 0.01
#: The burring shift must exceed this many standard deviations of the smoothed free noise.
NOISE_FACTOR = 5.0
#: Target number of blocks for the batch-means standard error.
BLOCKS = 20
#: Default relative search band for the spindle frequency (spindles slow under load).
SEARCH_FRACTION = 0.02
_ITERATIONS = 4
_MIN_WINDOW_S = 0.1  # below this the burring window's FFT is too coarse: use the recording


class AnalysisError(ValueError):
    """A recording (or signal) that cannot be analysed; the message says why."""


# --- validation ------------------------------------------------------------------------------


def _signal(x: np.ndarray, name: str = "x", min_len: int = 4) -> np.ndarray:
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


def _force(force_N: np.ndarray) -> np.ndarray:
    try:
        arr = np.asarray(force_N, dtype=np.float64)
    except (TypeError, ValueError):
        raise AnalysisError("force_N is not numeric") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise AnalysisError(f"force_N must have shape (n, 3), got {arr.shape}")
    if not np.isfinite(arr).all():
        raise AnalysisError(f"force_N holds {int((~np.isfinite(arr)).sum())} NaN/inf value(s)")
    return arr


def _positive(value: float, name: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise AnalysisError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out) or out <= 0.0:
        raise AnalysisError(f"{name} must be finite and > 0, got {out}")
    return out


def _check_nyquist(sample_rate_hz: float, spindle_hz: float, what: str = "") -> None:
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


def _refine_frequency(x: np.ndarray, sample_rate_hz: float, frequency_hz: float,
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


def _sine_fits(x: np.ndarray, sample_rate_hz: float, frequency_hz: float
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
    x = _signal(x)
    sample_rate_hz = _positive(sample_rate_hz, "sample_rate_hz")
    frequency_hz = _positive(frequency_hz, "frequency_hz")
    if frequency_hz >= sample_rate_hz / 2.0:
        raise AnalysisError(f"frequency {frequency_hz:g} Hz is not below the Nyquist frequency "
                            f"{sample_rate_hz / 2.0:g} Hz: it aliases")
    if not 0.0 <= search_fraction < 0.5:
        raise AnalysisError(f"search_fraction must be in [0, 0.5), got {search_fraction}")
    column = x[:, None]
    if refine and search_fraction > 0.0:
        frequency_hz = _refine_frequency(column, sample_rate_hz, frequency_hz, search_fraction)
    return _sine_fits(column, sample_rate_hz, frequency_hz)[0][0]


# --- the thesis's peak method and the FFT ----------------------------------------------------


def peak_amplitude(x: np.ndarray) -> float:
    """The thesis's vibration amplitude of x (n,): (mean of the upper peaks − mean of the lower
    peaks) / 2 of the mean-removed signal. Upper peaks are local maxima above the mean, lower
    peaks local minima below it (``scipy.signal.find_peaks``). 0 if there are none.

    Biased when a cycle has few samples: at 3 per cycle the sampled extremes fall short of the
    crest (0.75–0.87 of the amplitude, by phase), and noise adds to them.
    """
    y = _signal(x, min_len=3)
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
    sample_rate_hz = _positive(sample_rate_hz, "sample_rate_hz")
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


# --- segmentation ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # holds arrays: compare fields, not these
class Segments:
    """Where a recording burrs, and its free-spinning baseline. Indices are samples.

    Attributes:
        burring: [start, stop) the analysed burring window (the run with ``trim_fraction``
            cut from each end, away from the transitions).
        burring_full: [start, stop) the whole detected burring run (half-height crossings).
        non_burring: the free-spinning runs the baseline was fitted on, each [start, stop)
            (before and after the burring run; transitions and a guard excluded).
        baseline_N: (2, 3) per axis, the linear baseline's offset (N) at t = 0 (the first
            sample) and slope (N/s): the dynamometer's drift. Slope 0 when free-spinning
            data exist on one side only.
        smoothing_samples: the moving-average length (whole spindle periods, ≥ 10 ms).
        spindle_hz: the spindle frequency the smoothing was tuned to.
    """

    burring: tuple[int, int]
    burring_full: tuple[int, int]
    non_burring: tuple[tuple[int, int], ...]
    baseline_N: np.ndarray
    smoothing_samples: int = 0
    spindle_hz: float = float("nan")

    def baseline_at(self, t_s: np.ndarray) -> np.ndarray:
        """(len(t_s), 3) the baseline at times t_s (s from the first sample)."""
        t = np.asarray(t_s, dtype=np.float64)[:, None]
        return self.baseline_N[0] + self.baseline_N[1] * t


def smoothing_samples(sample_rate_hz: float, spindle_hz: float) -> int:
    """A moving-average length that spans ≥ SMOOTHING_MIN_S and (nearly) whole spindle
    periods, so it nulls the tone: the shortest length in [min, 4·min] with a gain < 1e-6 at
    spindle_hz, else the one with the least gain."""
    n_min = max(math.ceil(SMOOTHING_MIN_S * sample_rate_hz),
                math.ceil(sample_rate_hz / spindle_hz), 2)
    lengths = np.arange(n_min, 4 * n_min + 1)
    ratio = spindle_hz / sample_rate_hz
    gain = np.abs(np.sin(np.pi * lengths * ratio) / (lengths * np.sin(np.pi * ratio)))
    good = np.flatnonzero(gain < 1e-6)
    return int(lengths[good[0]] if len(good) else lengths[np.argmin(gain)])


def _runs(mask: np.ndarray, min_len: int
          ) -> tuple[tuple[int, int], tuple[int, int]] | None:
    """The longest run of True in mask, [start, stop), and the span from the first to the last
    run at least ``min_len`` long (shorter ones, away from the longest, are noise); or None."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    if len(edges) == 0:
        return None
    starts, stops = edges[0::2], edges[1::2]
    lengths = stops - starts
    i = int(np.argmax(lengths))
    keep = lengths >= min_len
    keep[i] = True
    return (int(starts[i]), int(stops[i])), (int(starts[keep].min()), int(stops[keep].max()))


def _free_sides(d: np.ndarray, run: tuple[int, int], span: tuple[int, int], guard: int
                ) -> tuple[tuple[int, int], tuple[int, int]]:
    """The free-spinning ranges before and after the burring ``span`` (all burring runs, the
    longest ``run`` among them) in d (m,), excluding the transitions (where d has not yet
    fallen near its free level) and ``guard`` samples beyond them."""
    a, b = span
    m = len(d)
    # The free level from the outer quarter of each side: nearest the ends, furthest from the
    # transitions (by protocol the recording starts and ends spinning free).
    outside = np.concatenate([d[: max(guard, a // 4)] if a else d[:0],
                              d[min(m - guard, b + 3 * (m - b) // 4):] if b < m else d[:0]])
    if len(outside) == 0:
        return (0, 0), (m, m)
    free_level = float(np.median(outside))
    spread = 1.4826 * float(np.median(np.abs(outside - free_level)))
    height = float(np.median(d[slice(*run)])) - free_level
    low = free_level + max(0.02 * height, 3.0 * spread)
    quiet_before = np.flatnonzero(d[:a] <= low)
    quiet_after = np.flatnonzero(d[b:] <= low)
    left_stop = max(0, (int(quiet_before[-1]) + 1 if len(quiet_before) else 0) - guard)
    right_start = min(m, (b + int(quiet_after[0]) if len(quiet_after) else m) + guard)
    return (0, left_stop), (right_start, m)


def _fit_baseline(t_s: np.ndarray, s: np.ndarray, sides: list[tuple[int, int]]) -> np.ndarray:
    """(2, 3) offset and slope: linear with free data on both sides, else constant."""
    index = np.concatenate([np.arange(*side) for side in sides])
    if len(sides) == 2:
        design = np.column_stack([np.ones(len(index)), t_s[index]])
        coef, *_ = np.linalg.lstsq(design, s[index], rcond=None)
        return coef
    return np.vstack([s[index].mean(axis=0), np.zeros(3)])


def find_segments(force_N: np.ndarray, sample_rate_hz: float, spindle_hz: float | None = None,
                  *, trim_fraction: float = 0.1, min_burring_s: float = 0.05) -> Segments:
    """The burring run and the free-spinning baseline of force_N (n, 3).

    Assumes the thesis's protocol: the recording starts and ends with the drill spinning free
    (if only one end is free, the baseline is a constant from that end). The force is smoothed
    by a moving average over whole spindle periods (``spindle_hz``, else the FFT peak), which
    removes the tone; burring is where the smoothed, baseline-corrected force vector's
    magnitude exceeds half-way between the free and burring levels (first split by Otsu's
    threshold along the principal direction, then iterated with the baseline). The longest
    such run is analysed; the baseline (linear in time: drift) is fitted on the free samples
    before the first and after the last burring run (runs shorter than two smoothing windows
    are taken as noise), the transitions and one smoothing window beyond them excluded.

    Raises:
        AnalysisError: aliasing (rate ≤ 2 × spindle), no burring clearly above the smoothed
            noise (< 5σ), burring shorter than ``min_burring_s``, no free-spinning data, a
            recording too short for the smoothing, bad arguments.
    """
    force = _force(force_N)
    sample_rate_hz = _positive(sample_rate_hz, "sample_rate_hz")
    if not 0.0 <= trim_fraction < 0.5:
        raise AnalysisError(f"trim_fraction must be in [0, 0.5), got {trim_fraction}")
    if not min_burring_s >= 0.0:
        raise AnalysisError(f"min_burring_s must be ≥ 0, got {min_burring_s}")
    if spindle_hz is None:
        spindle_hz = dominant_frequency(force, sample_rate_hz, min_hz=MIN_SPINDLE_HZ)
    spindle_hz = _positive(spindle_hz, "spindle_hz")
    _check_nyquist(sample_rate_hz, spindle_hz)
    n = len(force)
    width = smoothing_samples(sample_rate_hz, spindle_hz)
    if n < 4 * width:
        raise AnalysisError(f"{n} samples ({n / sample_rate_hz:.3g} s) is too short for a "
                            f"smoothing window of {width} samples; record longer")

    # Moving average over [j, j + width): sample j of s is centred on raw (j + (width−1)/2).
    s = ndimage.uniform_filter1d(force, width, axis=0, mode="nearest")[
        width // 2 : width // 2 + n - width + 1]
    m = len(s)
    t_s = (np.arange(m) + (width - 1) / 2.0) / sample_rate_hz
    scale = float(np.abs(force).max())

    # A first split, no baseline needed: Otsu along the direction the shift dominates.
    centred = s - s.mean(axis=0)
    direction = np.linalg.svd(centred, full_matrices=False)[2][0]
    p = centred @ direction
    if np.ptp(p) <= 1e-12 * max(scale, 1e-300):
        raise AnalysisError("no burring found: the smoothed force is constant")
    high = p > threshold_otsu(p)
    k = max(1, min(width, m // 10))
    start_high, end_high = high[:k].mean() > 0.5, high[-k:].mean() > 0.5
    if start_high == end_high:
        free_high = start_high
    else:  # free at one end only: the free class is the one nearer zero (a zeroed sensor)
        free_high = bool(np.linalg.norm(s[high].mean(axis=0))
                         < np.linalg.norm(s[~high].mean(axis=0)))
    burring = ~high if free_high else high
    runs = _runs(burring, 2 * width)
    if runs is None or burring.all():
        raise AnalysisError("no burring found: no shift of the smoothed force")
    d = np.linalg.norm(s - s[~burring].mean(axis=0), axis=1)

    # Baseline ↔ threshold, a few rounds. Every burring run (a lift-off splits one) is kept out
    # of the baseline; the longest is the one analysed.
    for _ in range(_ITERATIONS):
        baseline, sides = _baseline(t_s, s, d, runs, width)
        d = np.linalg.norm(s - baseline[0] - baseline[1] * t_s[:, None], axis=1)
        free = np.concatenate([d[slice(*side)] for side in sides])
        threshold = 0.5 * (float(np.median(free)) + float(np.median(d[slice(*runs[0])])))
        new_runs = _runs(d > threshold, 2 * width)
        if new_runs is None or new_runs == runs:
            break
        runs = new_runs
    else:
        baseline, sides = _baseline(t_s, s, d, runs, width)
    run = runs[0]

    residual = np.concatenate([s[slice(*side)] for side in sides]) - _line(
        baseline, np.concatenate([t_s[slice(*side)] for side in sides]))
    noise = float(np.sqrt(np.sum(np.var(residual, axis=0))))
    in_run = s[slice(*run)] - _line(baseline, t_s[slice(*run)])
    shift = float(np.linalg.norm(in_run.mean(axis=0)))
    if shift <= max(NOISE_FACTOR * noise, 1e-9 * scale):
        raise AnalysisError(
            f"no burring found: the largest shift of the smoothed force, {shift:.3g} N, is not "
            f"clearly above its free-spinning noise (σ = {noise:.3g} N; needs "
            f"{NOISE_FACTOR:g}σ) — or the recording has no free spinning to compare with: it "
            "must start and end with the drill spinning free")

    # Smoothed j is centred on raw j + (width − 1)/2: the half-height crossings of a step fall
    # at raw run[0] + (width − 1)//2 going up and run[1] + width//2 coming down.
    start, stop = run[0] + (width - 1) // 2, run[1] + width // 2
    if (stop - start) / sample_rate_hz < min_burring_s:
        raise AnalysisError(f"burring lasts {(stop - start) / sample_rate_hz:.3g} s (samples "
                            f"{start}–{stop}), shorter than min_burring_s = {min_burring_s:g} s")
    cut = round(trim_fraction * (stop - start))
    window = (start + cut, stop - cut)
    if window[1] - window[0] < max(8, 2.0 * sample_rate_hz / spindle_hz):
        raise AnalysisError(f"the analysed burring window, samples {window[0]}–{window[1]}, "
                            "holds fewer than two spindle periods")
    # Smoothed sample j averaged raw [j, j + width): a side [p, q) used raw [p, q + width − 1).
    raw_sides = tuple((p0, min(n, q0 + width - 1)) for p0, q0 in sides)
    return Segments(burring=window, burring_full=(start, stop), non_burring=raw_sides,
                    baseline_N=baseline, smoothing_samples=width, spindle_hz=spindle_hz)


def _line(baseline: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    return baseline[0] + baseline[1] * t_s[:, None]


def _baseline(t_s: np.ndarray, s: np.ndarray, d: np.ndarray,
              runs: tuple[tuple[int, int], tuple[int, int]], width: int
              ) -> tuple[np.ndarray, list[tuple[int, int]]]:
    before, after = _free_sides(d, runs[0], runs[1], width)
    sides = [side for side in (before, after) if side[1] - side[0] >= width]
    if not sides:
        raise AnalysisError(
            "no non-burring (free-spinning) data: the recording must start and/or end with the "
            "drill spinning free (the thesis's protocol), for the baseline")
    return _fit_baseline(t_s, s, sides), sides


# --- the analysis ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)  # holds arrays: compare fields, not these
class Vibration:
    """The spindle vibration of one region.

    Attributes:
        amplitude_fit_N: (3,) per axis, least-squares sinusoid fit.
        amplitude_peaks_N: (3,) per axis, the thesis's peak method.
        resultant_fit_N: |Fv| = √(Fvx² + Fvy² + Fvz²) of the fit amplitudes (thesis §2.5.2).
        resultant_peaks_N: the same of the peak amplitudes.
        frequency_hz: the fit's refined frequency (shared by the three axes).
    """

    amplitude_fit_N: np.ndarray
    amplitude_peaks_N: np.ndarray
    resultant_fit_N: float
    resultant_peaks_N: float
    frequency_hz: float


@dataclass(frozen=True, eq=False)  # holds arrays: compare fields, not these
class RecordingAnalysis:
    """What :func:`analyse` found. Forces in the dynamometer frame, signs as measured.

    Attributes:
        mean_force_N: (3,) mean over the analysed burring window minus the baseline.
        mean_force_sem_N: (3,) its standard error: batch means over blocks of whole spindle
            periods in the window, plus the baseline's own uncertainty (likewise from blocks).
        segments: the burring window, the free runs and the baseline.
        burring, non_burring: the vibration in each region.
        ratio_fit, ratio_peaks: burring / non-burring resultant amplitude (thesis Fig. 14).
        dominant_frequency_hz: by FFT over the burring window (the whole recording if the
            window is shorter than 0.1 s).
        spindle_hz: the frequency the analysis used: rpm/60 if given, else the FFT peak.
    """

    mean_force_N: np.ndarray
    mean_force_sem_N: np.ndarray
    segments: Segments
    burring: Vibration
    non_burring: Vibration
    ratio_fit: float
    ratio_peaks: float
    dominant_frequency_hz: float
    spindle_hz: float | None


def _vibration(regions: list[np.ndarray], sample_rate_hz: float, spindle_hz: float
               ) -> tuple[Vibration, list[tuple[list[SineFit], np.ndarray]]]:
    """Each region (n_i, 3) fitted on its own (phase need not carry across a gap), the
    amplitudes averaged weighted by length."""
    weights = np.array([len(r) for r in regions], dtype=np.float64)
    fits, amp_fit, amp_peaks, freq = [], [], [], []
    for region in regions:
        f = _refine_frequency(region, sample_rate_hz, spindle_hz, SEARCH_FRACTION)
        axis_fits, tone = _sine_fits(region, sample_rate_hz, f)
        fits.append((axis_fits, tone))
        amp_fit.append([a.amplitude_N for a in axis_fits])
        amp_peaks.append([peak_amplitude(region[:, j]) for j in range(3)])
        freq.append(f)
    w = weights / weights.sum()
    fit = w @ np.array(amp_fit)
    peaks = w @ np.array(amp_peaks)
    return Vibration(amplitude_fit_N=fit, amplitude_peaks_N=peaks,
                     resultant_fit_N=float(np.linalg.norm(fit)),
                     resultant_peaks_N=float(np.linalg.norm(peaks)),
                     frequency_hz=float(w @ np.array(freq))), fits


def _ratio(num: float, den: float) -> float:
    return num / den if den > 0.0 else float("nan")


def _block_means(x: np.ndarray, length: int) -> np.ndarray:
    k = len(x) // length
    return x[: k * length].reshape(k, length, -1).mean(axis=1)


def analyse(recording: Recording, rpm: float | None = None, *, trim_fraction: float = 0.1,
            min_burring_s: float = 0.05) -> RecordingAnalysis:
    """Mean force, its standard error, vibration and dominant frequency of a recording made by
    the thesis's protocol (free spin, burring, free spin; see :func:`find_segments`).

    ``rpm`` fixes the spindle frequency (|rpm|/60; the fit still refines it ±2 %); without it
    the FFT peak above 20 Hz is taken.

    Raises:
        AnalysisError: as :func:`find_segments`, prefixed with the recording's source.
    """
    try:
        return _analyse(recording, rpm, trim_fraction, min_burring_s)
    except AnalysisError as exc:
        raise AnalysisError(f"{recording.source}: {exc}") from None


def _analyse(recording: Recording, rpm: float | None, trim_fraction: float,
             min_burring_s: float) -> RecordingAnalysis:
    force = recording.force_N
    fs = recording.sample_rate_hz
    if rpm is not None:
        try:
            rpm = float(rpm)
        except (TypeError, ValueError):
            raise AnalysisError(f"rpm must be a number, got {rpm!r}") from None
        if not math.isfinite(rpm) or rpm == 0.0:
            raise AnalysisError(f"rpm must be finite and non-zero, got {rpm}")
        spindle_hz = abs(rpm) / 60.0
        _check_nyquist(fs, spindle_hz, f" ({abs(rpm):g} rpm)")
        min_hz = min(MIN_SPINDLE_HZ, 0.5 * spindle_hz)
    else:
        spindle_hz = dominant_frequency(force, fs, min_hz=MIN_SPINDLE_HZ)
        min_hz = MIN_SPINDLE_HZ
    seg = find_segments(force, fs, spindle_hz, trim_fraction=trim_fraction,
                        min_burring_s=min_burring_s)
    t_s = recording.t_s
    corrected = force - seg.baseline_at(t_s)
    a, b = seg.burring
    window = corrected[a:b]

    burring, ((burr_fits, burr_tone),) = _vibration([window], fs, spindle_hz)
    free_regions = [corrected[p:q] for p, q in seg.non_burring]
    free, free_fits = _vibration(free_regions, fs, spindle_hz)
    mean = np.array([f.offset_N for f in burr_fits])

    # Batch means: blocks of whole spindle periods, the fitted tone removed first.
    period = fs / burring.frequency_hz
    free_periods = sum(len(r) for r in free_regions) / period
    per_block = max(2, int(min(len(window) / period, free_periods) // BLOCKS))
    length = max(8, round(per_block * period))
    blocks = _block_means(window - burr_tone, length)
    sem2 = (np.var(blocks, axis=0, ddof=1) / len(blocks) if len(blocks) >= 2
            else np.full(3, np.nan))
    free_blocks, free_t = [], []
    for (p, q), (_, tone) in zip(seg.non_burring, free_fits, strict=True):
        means = _block_means(corrected[p:q] - tone, length)
        free_blocks.append(means)
        free_t.append(t_s[p:q][: len(means) * length].reshape(len(means), length).mean(axis=1))
    fb, ft = np.concatenate(free_blocks), np.concatenate(free_t)
    linear = len(seg.non_burring) == 2
    design = np.column_stack([np.ones(len(ft)), ft]) if linear else np.ones((len(ft), 1))
    dof = len(ft) - design.shape[1]
    if dof >= 1:
        # The baseline's error averaged over the window, from the free blocks' scatter.
        g = np.array([1.0, t_s[a:b].mean()]) if linear else np.ones(1)
        leverage = float(g @ np.linalg.pinv(design.T @ design) @ g)
        sem2 = sem2 + leverage * np.sum(fb ** 2, axis=0) / dof
    else:
        sem2 = np.full(3, np.nan)

    if b - a >= max(64, _MIN_WINDOW_S * fs):
        dominant = dominant_frequency(window, fs, min_hz=min_hz)
    else:
        dominant = dominant_frequency(force, fs, min_hz=min_hz)
    return RecordingAnalysis(
        mean_force_N=mean, mean_force_sem_N=np.sqrt(sem2), segments=seg, burring=burring,
        non_burring=free, ratio_fit=_ratio(burring.resultant_fit_N, free.resultant_fit_N),
        ratio_peaks=_ratio(burring.resultant_peaks_N, free.resultant_peaks_N),
        dominant_frequency_hz=dominant, spindle_hz=spindle_hz)
