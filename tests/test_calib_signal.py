"""Segments, mean force and vibration of synthetic recordings of known truth
(burrforce.server.calib.signal, .synthetic)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.calib.recording import Recording
from burrforce.server.calib.segments import find_segments
from burrforce.server.calib.signal import analyse
from burrforce.server.calib.synthetic import synthetic_recording
from burrforce.server.calib.tones import (
    AnalysisError,
    dominant_frequency,
    peak_amplitude,
    sine_fit,
)

FS = 3000.0
MEAN = np.array([2.0, -1.0, 5.0])


def tone(f_hz: float, amplitude: float, phase: float, n: int = 3000, fs: float = FS):
    return amplitude * np.cos(2.0 * np.pi * f_hz * np.arange(n) / fs + phase)


# --- mean force ------------------------------------------------------------------------------


@pytest.mark.parametrize("phase", [0.0, 0.4, 1.3, 2.9])
def test_noise_free_mean_with_drift_and_tone(phase):
    rec = synthetic_recording(MEAN, tone_phase_rad=(phase, phase + 1.0, phase + 2.0),
                              drift_N_s=(0.05, -0.05, 0.05), offset_N=(0.1, 0.2, -0.3))
    a = analyse(rec, rpm=60000.0)
    assert np.allclose(a.mean_force_N, MEAN, rtol=1e-3, atol=0.0)
    assert np.abs(a.mean_force_N - MEAN).max() < 1e-9  # in fact exact
    assert np.allclose(a.segments.baseline_N, [[0.1, 0.2, -0.3], [0.05, -0.05, 0.05]],
                       atol=1e-9)


@settings(max_examples=examples(25))
@given(mean=st.tuples(*[st.floats(-20.0, 20.0)] * 3).filter(lambda m: np.linalg.norm(m) > 1.0),
       drift=st.tuples(*[st.floats(-0.05, 0.05)] * 3),
       spindle_hz=st.floats(700.0, 1300.0), phase=st.floats(0.0, 6.3))
def test_noise_free_mean_property(mean, drift, spindle_hz, phase):
    rec = synthetic_recording(mean, drift_N_s=drift, spindle_hz=spindle_hz,
                              tone_phase_rad=phase, free_s=0.4, burring_s=0.8)
    a = analyse(rec, rpm=spindle_hz * 60.0)
    assert np.linalg.norm(a.mean_force_N - mean) <= 1e-3 * np.linalg.norm(mean)


def test_spindle_slower_than_told():
    # 59 400 rpm under load, told 60 000: the fit finds 990 Hz; the mean stays within 0.1 %.
    rec = synthetic_recording(MEAN, spindle_hz=990.0, drift_N_s=0.05, seed=2)
    a = analyse(rec, rpm=60000.0)
    assert a.spindle_hz == 1000.0
    assert a.burring.frequency_hz == pytest.approx(990.0, abs=1e-3)
    assert a.non_burring.frequency_hz == pytest.approx(990.0, abs=1e-3)
    assert np.allclose(a.burring.amplitude_fit_N, 0.3, rtol=1e-4)
    assert np.allclose(a.mean_force_N, MEAN, rtol=1e-3)


def test_noisy_mean_within_three_sem():
    rec = synthetic_recording(MEAN, noise_N=0.5, drift_N_s=0.05, seed=11)
    a = analyse(rec, rpm=60000.0)
    z = (a.mean_force_N - MEAN) / a.mean_force_sem_N
    assert np.all(np.abs(z) < 3.0)
    assert np.all(a.mean_force_sem_N < 0.03)


def test_sem_is_honest():
    # z = (estimate − truth) / SEM over 40 seeds × 3 axes: its spread should be near 1 (the
    # SEM counts the window's noise and the baseline's).
    z = []
    for seed in range(40):
        rec = synthetic_recording(MEAN, noise_N=0.5, drift_N_s=(0.03, -0.02, 0.0), seed=seed,
                                  free_s=0.3, burring_s=0.8)
        a = analyse(rec, rpm=60000.0)
        z.append((a.mean_force_N - MEAN) / a.mean_force_sem_N)
    z = np.ravel(z)
    assert 0.8 < z.std() < 1.25
    assert abs(z.mean()) < 0.4


# --- vibration amplitude: fit vs the thesis's peaks --------------------------------------------


@pytest.mark.parametrize("phase", [0.0, 0.2, 0.5, 0.8, 1.0])
def test_peak_method_biased_fit_not_at_three_samples_per_cycle(phase):
    x = tone(1000.0, 0.3, phase)
    assert sine_fit(x, FS, 1000.0).amplitude_N == pytest.approx(0.3, rel=1e-6)
    ratio = peak_amplitude(x) / 0.3
    assert 0.74 < ratio < 0.87  # sampled extremes fall 13–25 % short of the crest
    assert 1.0 - ratio > 0.1


def test_fit_unbiased_over_phases_and_seeds():
    rng = np.random.default_rng(5)
    fits, peaks = [], []
    for _ in range(60):
        x = tone(1000.0, 0.3, rng.uniform(0, 2 * np.pi)) + 0.05 * rng.standard_normal(3000)
        fits.append(sine_fit(x, FS, 1000.0).amplitude_N / 0.3)
        peaks.append(peak_amplitude(x) / 0.3)
    assert np.mean(fits) == pytest.approx(1.0, abs=0.01)
    assert np.mean(peaks) < 0.9


def test_noise_biases_peaks_upward():
    rng = np.random.default_rng(6)
    by_noise = []
    for noise in (0.0, 0.1, 0.3):
        runs = [tone(990.0, 0.3, rng.uniform(0, 2 * np.pi)) + noise * rng.standard_normal(3000)
                for _ in range(10)]
        by_noise.append((np.mean([peak_amplitude(x) for x in runs]) / 0.3,
                         np.mean([sine_fit(x, FS, 990.0).amplitude_N for x in runs]) / 0.3))
    peaks = [p for p, _ in by_noise]
    assert peaks[0] < peaks[1] < peaks[2] and peaks[2] > 1.15
    assert all(abs(f - 1.0) < 0.02 for _, f in by_noise)


def test_sine_fit_recovers_phase_offset_and_frequency():
    x = 1.5 + tone(990.0, 0.7, -2.0)
    fit = sine_fit(x, FS, 1000.0)
    assert fit.frequency_hz == pytest.approx(990.0, abs=1e-4)
    assert (fit.amplitude_N, fit.offset_N) == pytest.approx((0.7, 1.5), rel=1e-6)
    assert fit.phase_rad == pytest.approx(-2.0, abs=1e-3)
    assert fit.rms_residual_N < 1e-6
    stale = sine_fit(x, FS, 1000.0, refine=False)  # 10 Hz off over 1 s: the tone beats away
    assert stale.amplitude_N < 0.1


@pytest.mark.parametrize("f_hz", [990.0, 1000.0, 1234.5, 517.3])
def test_dominant_frequency(f_hz):
    rng = np.random.default_rng(int(f_hz))
    x = tone(f_hz, 0.3, 1.0, n=6000) + 0.1 * rng.standard_normal(6000)
    assert dominant_frequency(x, FS) == pytest.approx(f_hz, abs=0.5)
    xyz = np.column_stack([x, 0.5 * x, 0.1 * rng.standard_normal(6000) + 3.0])
    assert dominant_frequency(xyz, FS) == pytest.approx(f_hz, abs=0.5)


def test_dominant_frequency_ignores_dc_and_min_hz():
    x = 5.0 + 0.01 * np.arange(3000) + tone(8.0, 2.0, 0.0) + tone(1000.0, 0.3, 0.0)
    assert dominant_frequency(x, FS, min_hz=20.0) == pytest.approx(1000.0, abs=0.5)


@pytest.mark.parametrize(("gain", "ratio"), [(1.0, 1.0), (1.5, 1.5)])
def test_burring_to_free_ratio(gain, ratio):
    rec = synthetic_recording(MEAN, burring_tone_gain=gain, noise_N=0.05, seed=4,
                              tone_amplitude_N=(0.3, 0.2, 0.4))
    a = analyse(rec, rpm=60000.0)
    assert a.ratio_fit == pytest.approx(ratio, rel=0.01)
    assert a.ratio_peaks == pytest.approx(ratio, rel=0.05)
    assert a.non_burring.resultant_fit_N == pytest.approx(np.sqrt(0.29), rel=0.01)
    assert a.non_burring.resultant_peaks_N < 0.9 * np.sqrt(0.29)  # the thesis's method
    assert a.dominant_frequency_hz == pytest.approx(1000.0, abs=0.5)


# --- segments --------------------------------------------------------------------------------


def _truth(free_s=1.0, burring_s=2.0, ramp_s=0.1):
    return (free_s + ramp_s / 2) * FS, (free_s + 1.5 * ramp_s + burring_s) * FS


@pytest.mark.parametrize("rpm", [60000.0, None])
def test_segment_boundaries(rpm):
    rec = synthetic_recording(MEAN, noise_N=0.3, drift_N_s=0.05, seed=8)
    seg = analyse(rec, rpm=rpm).segments
    width = seg.smoothing_samples
    assert width >= 0.01 * FS
    start, stop = _truth()
    assert abs(seg.burring_full[0] - start) <= width
    assert abs(seg.burring_full[1] - stop) <= width
    length = seg.burring_full[1] - seg.burring_full[0]
    assert seg.burring == (seg.burring_full[0] + round(0.1 * length),
                           seg.burring_full[1] - round(0.1 * length))
    (p0, p1), (q0, q1) = seg.non_burring
    assert p0 == 0 and q1 == len(rec.force_N)
    assert p1 < 1.0 * FS and q0 > (1.0 + 0.2 + 2.0) * FS  # transitions excluded


def test_free_data_on_one_side_only():
    rec = synthetic_recording(MEAN, offset_N=(0.2, 0.0, -0.1), seed=9)
    cut = Recording(rec.force_N[: int(3.0 * FS)], FS, "truncated while burring")
    seg = find_segments(cut.force_N, FS, 1000.0)
    assert len(seg.non_burring) == 1 and seg.non_burring[0][0] == 0
    assert np.allclose(seg.baseline_N, [[0.2, 0.0, -0.1], [0.0, 0.0, 0.0]], atol=1e-9)
    assert abs(seg.burring_full[0] - _truth()[0]) <= seg.smoothing_samples
    assert seg.burring_full[1] >= len(cut.force_N) - seg.smoothing_samples  # runs to the end
    a = analyse(cut, 60000.0)
    assert np.allclose(a.mean_force_N, MEAN, rtol=1e-3)


def test_lift_off_keeps_the_longest_run_and_a_clean_baseline():
    rec = synthetic_recording(MEAN, drift_N_s=0.05, offset_N=0.1, seed=12)
    force = rec.force_N.copy()
    t = rec.t_s
    force[(t > 1.8) & (t < 1.9)] -= MEAN  # the burr lifted off for 0.1 s
    seg = analyse(Recording(force, FS, "lift-off"), 60000.0).segments
    assert abs(seg.burring_full[0] - 1.9 * FS) <= seg.smoothing_samples
    assert abs(seg.burring_full[1] - _truth()[1]) <= seg.smoothing_samples
    assert seg.non_burring[0][1] < 1.0 * FS  # the first, shorter run is not free data
    assert np.allclose(seg.baseline_N, [[0.1] * 3, [0.05] * 3], atol=1e-9)


def test_negative_force_and_no_rpm():
    rec = synthetic_recording(-MEAN, noise_N=0.1, seed=10, spindle_hz=750.0)
    a = analyse(rec)
    assert a.spindle_hz == pytest.approx(750.0, abs=0.5)
    assert np.allclose(a.mean_force_N, -MEAN, atol=0.02)


# --- refusals --------------------------------------------------------------------------------


def test_no_burring():
    rec = synthetic_recording((0.0, 0.0, 0.0), noise_N=0.2, seed=1)
    with pytest.raises(AnalysisError, match=r"synthetic.*no burring found"):
        analyse(rec, 60000.0)
    tiny = synthetic_recording((0.005, 0.0, 0.0), noise_N=0.2, seed=1)
    with pytest.raises(AnalysisError, match=r"not clearly above its free-spinning noise"):
        analyse(tiny, 60000.0)
    flat = synthetic_recording((0.0, 0.0, 0.0), seed=1)  # a pure tone: nothing shifts
    with pytest.raises(AnalysisError, match=r"no burring found"):
        analyse(flat, 60000.0)


def test_burring_too_short():
    rec = synthetic_recording(MEAN, burring_s=0.01, ramp_s=0.005, seed=1)
    with pytest.raises(AnalysisError, match=r"burring lasts 0\.01\d* s .*shorter than "
                                            r"min_burring_s = 0\.05 s"):
        analyse(rec, 60000.0)
    assert analyse(rec, 60000.0, min_burring_s=0.005).segments.burring_full[1] > 0


def test_no_free_spinning_data():
    # 10 ms of free spin each side, less than the transitions and their guard.
    rec = synthetic_recording(MEAN, free_s=0.01, ramp_s=0.05, burring_s=1.0, seed=1)
    with pytest.raises(AnalysisError, match=r"no non-burring \(free-spinning\) data.*"
                                            r"start and/or end"):
        analyse(rec, 60000.0)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"rpm": 120000.0}, r"3000 Hz is not above twice the spindle frequency 2000 Hz "
                        r"\(120000 rpm\): the spindle tone aliases"),
    ({"rpm": 90000.0}, r"aliases"),
    ({"rpm": 0.0}, r"rpm must be finite and non-zero"),
    ({"rpm": float("nan")}, r"rpm must be finite"),
    ({"rpm": 60000.0, "trim_fraction": 0.5}, r"trim_fraction must be in \[0, 0\.5\)"),
])
def test_analyse_refuses(kwargs, message):
    rec = synthetic_recording(MEAN, seed=1, free_s=0.3, burring_s=0.5)
    with pytest.raises(AnalysisError, match=message):
        analyse(rec, **kwargs)


def test_function_refusals():
    x = tone(1000.0, 0.3, 0.0)
    with pytest.raises(AnalysisError, match=r"not below the Nyquist frequency 1500 Hz"):
        sine_fit(x, FS, 1500.0)
    with pytest.raises(AnalysisError, match=r"NaN/inf"):
        sine_fit(np.r_[x, np.nan], FS, 1000.0)
    with pytest.raises(AnalysisError, match=r"must be 1-D"):
        sine_fit(np.zeros((10, 3)), FS, 1000.0)
    with pytest.raises(AnalysisError, match=r"no oscillation"):
        dominant_frequency(np.zeros(100), FS)
    with pytest.raises(AnalysisError, match=r"force_N must have shape \(n, 3\)"):
        find_segments(np.zeros((100, 2)), FS, 1000.0)
    with pytest.raises(AnalysisError, match=r"too short for a smoothing window"):
        find_segments(np.zeros((100, 3)), FS, 1000.0)
    assert peak_amplitude(np.arange(10.0)) == 0.0  # no extrema, no oscillation


@pytest.mark.parametrize("rate_hz, spindle_hz", [(3000.0, 1000.0), (3000.0, 300.0),
                                                 (2500.0, 1000.0), (3000.0, 600.0)])
def test_a_noise_free_step_is_found_to_the_sample_for_odd_and_even_windows(rate_hz,
                                                                            spindle_hz):
    """A 0 → 1 N step over raw samples [1200, 4800): the run is exactly that, whatever the
    smoothing window's parity (an even one used to end a sample early)."""
    force = np.zeros((6000, 3))
    force[1200:4800, 2] = 1.0
    seg = find_segments(force, rate_hz, spindle_hz)
    assert seg.burring_full == (1200, 4800), seg.smoothing_samples
