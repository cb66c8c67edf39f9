"""Where a dynamometer recording burrs (thesis §2.4): the drill spins free, cuts, and spins
free again; :func:`find_segments` finds the burring run and fits the dynamometer's drift on
the free-spinning samples around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.filters import threshold_otsu

from .tones import (
    MIN_SPINDLE_HZ,
    AnalysisError,
    as_force,
    check_nyquist,
    dominant_frequency,
    positive,
)

#: The moving average spans at least this long (and whole spindle periods).
SMOOTHING_MIN_S = 0.01
#: The burring shift must exceed this many standard deviations of the smoothed free noise.
NOISE_FACTOR = 5.0
_ITERATIONS = 4


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
    force = as_force(force_N)
    sample_rate_hz = positive(sample_rate_hz, "sample_rate_hz")
    if not 0.0 <= trim_fraction < 0.5:
        raise AnalysisError(f"trim_fraction must be in [0, 0.5), got {trim_fraction}")
    if not min_burring_s >= 0.0:
        raise AnalysisError(f"min_burring_s must be ≥ 0, got {min_burring_s}")
    if spindle_hz is None:
        spindle_hz = dominant_frequency(force, sample_rate_hz, min_hz=MIN_SPINDLE_HZ)
    spindle_hz = positive(spindle_hz, "spindle_hz")
    check_nyquist(sample_rate_hz, spindle_hz)
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
