"""Mean force and vibration of a dynamometer recording (thesis §2.4, §2.5.2; model.md).

A recording follows the thesis's protocol: the drill spins free (non-burring: mean ≈ 0 plus the
spindle tone), cuts (burring: the mean shifts by the cutting force, the tone stays), and spins
free again. ``segments.find_segments`` finds the burring run and fits the dynamometer's drift
on the free-spinning samples; :func:`analyse` measures, over the burring window:

- the mean force (baseline removed), jointly fitted with the spindle sinusoid so the tone
  cannot bias it, and an honest standard error (batch means over blocks of whole periods);
- the vibration amplitude per axis two ways: the thesis's peak method (``tones.peak_amplitude``,
  biased at 3 samples per cycle) and a least-squares sinusoid fit (``tones.sine_fit``,
  unbiased), their resultants and the burring / non-burring ratio (the thesis found ≈ 1);
- the dominant frequency by FFT (``tones.dominant_frequency``).

Problems with the data raise ``tones.AnalysisError`` (a ``ValueError``) saying what is wrong.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .recording import Recording
from .segments import Segments, find_segments
from .tones import (
    MIN_SPINDLE_HZ,
    SEARCH_FRACTION,
    AnalysisError,
    SineFit,
    check_nyquist,
    dominant_frequency,
    peak_amplitude,
    refine_frequency,
    sine_fits,
)

#: Target number of blocks for the batch-means standard error.
BLOCKS = 20
_MIN_WINDOW_S = 0.1  # below this the burring window's FFT is too coarse: use the recording


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
        f = refine_frequency(region, sample_rate_hz, spindle_hz, SEARCH_FRACTION)
        axis_fits, tone = sine_fits(region, sample_rate_hz, f)
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
        check_nyquist(fs, spindle_hz, f" ({abs(rpm):g} rpm)")
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
