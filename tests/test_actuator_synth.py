"""The vibration synthesizer: phase continuity, frequency and amplitude, perceptual mode,
silence after a stale stream, and the N → level map."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.actuators.base import AmplitudeMap
from burrforce.server.devices.actuators.synth import (
    MAX_CARRIER_FRACTION,
    Oscillator,
    Perceptual,
    fill_block,
)

RATE = 48_000.0

targets = st.lists(
    st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 2000.0), st.integers(16, 256)),
    min_size=1, max_size=30)


def _render(osc: Oscillator, plan) -> tuple[np.ndarray, float]:
    """Concatenated blocks for ``plan`` [(level, Hz, block frames)], and the largest
    per-sample amplitude ramp step."""
    blocks, ramp_step, previous = [], 0.0, 0.0
    for level, hz, n in plan:
        osc.set_target(level, hz)
        blocks.append(osc.block(n))
        ramp_step = max(ramp_step, abs(osc.level - previous) / (n - 1))
        previous = osc.level
    return np.concatenate(blocks), ramp_step


@given(targets)
def test_phase_continuous_across_blocks(plan):
    """No sample step exceeds what a sine at the highest frequency and amplitude moves per
    sample plus the amplitude ramp's step: no click at block edges or parameter changes."""
    osc = Oscillator(RATE)
    x, ramp_step = _render(osc, plan)
    f_max = max(hz for _, hz, _ in plan)
    a_max = max(level for level, _, _ in plan)
    bound = 2 * math.pi * f_max / RATE * a_max + ramp_step + 1e-6
    assert np.all(np.isfinite(x))
    assert np.max(np.abs(x)) <= a_max + 1e-6
    if x.size > 1:
        assert np.max(np.abs(np.diff(x.astype(np.float64)))) <= bound


@given(targets)
def test_phase_continuous_with_am(plan):
    osc = Oscillator(RATE, Perceptual("am", corner_hz=800.0, am_hz=250.0))
    x, ramp_step = _render(osc, plan)
    f_max = max(hz for _, hz, _ in plan)
    a_max = max(level for level, _, _ in plan)
    min_n = min(n for _, _, n in plan)
    # the raised-cosine envelope moves ≤ π·am/rate per sample, its depth ≤ 1/(n−1)
    bound = (2 * math.pi * f_max / RATE + math.pi * 250.0 / RATE + 1 / (min_n - 1)) * a_max \
        + ramp_step + 1e-6
    if x.size > 1:
        assert np.max(np.abs(np.diff(x.astype(np.float64)))) <= bound


def _spectrum_peak(x: np.ndarray) -> tuple[float, float]:
    """(frequency Hz of the largest bin, its sine amplitude) of a Hann-windowed rfft."""
    window = np.hanning(x.size)
    spectrum = np.abs(np.fft.rfft(x * window))
    k = int(np.argmax(spectrum))
    return k * RATE / x.size, 2 * spectrum[k] / window.sum()


@given(st.floats(50.0, 2000.0), st.floats(0.05, 1.0), st.integers(32, 128))
def test_frequency_and_amplitude_by_fft(hz, level, n):
    """A steady target comes out at its frequency (within one 1 Hz bin) and amplitude."""
    osc = Oscillator(RATE)
    osc.set_target(level, hz)
    osc.block(n)  # the ramp-in block
    x = np.concatenate([osc.block(n) for _ in range(48_000 // n + 1)])[:48_000]
    peak_hz, amplitude = _spectrum_peak(x)
    assert abs(peak_hz - hz) <= 1.0
    # Hann scalloping loses ≤ 15 % between bins; the peak sample is exact
    assert amplitude == pytest.approx(level, rel=0.16)
    # The samples straddle each crest: the largest is within half a sample period of it, so
    # at least level·cos(π·hz/RATE) (0.9914·level at 2 kHz), and never above the level.
    peak = float(np.max(np.abs(x)))
    assert level * math.cos(math.pi * hz / RATE) * (1 - 1e-3) - 1e-4 <= peak
    assert peak <= level * (1 + 1e-3) + 1e-4


@given(st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 2000.0),
                          st.integers(16, 256)), min_size=1, max_size=10),
       st.integers(16, 256))
def test_stale_ramps_to_zero_within_one_block_and_stays(plan, n):
    osc = Oscillator(RATE)
    _render(osc, plan)
    ramp = osc.block(n, stale=True)
    assert ramp[-1] == 0.0
    assert osc.silent
    for _ in range(5):  # no new target: silence, even without the stale flag
        assert not np.any(osc.block(n))
    osc.set_target(0.5, 300.0)  # a fresh target revives it
    osc.block(n)
    assert np.any(osc.block(n))


def test_zero_frequency_fades_out_at_the_old_pitch_without_dc():
    osc = Oscillator(RATE)
    osc.set_target(1.0, 500.0)
    osc.block(64)
    osc.set_target(1.0, 0.0)
    fade = osc.block(64)
    assert fade[-1] == 0.0 and osc.silent
    assert not np.any(osc.block(64))


def test_clamp_mode_moves_the_carrier_to_the_corner():
    osc = Oscillator(RATE, Perceptual("clamp", corner_hz=800.0))
    osc.set_target(0.5, 1500.0)
    osc.block(64)
    peak_hz, _ = _spectrum_peak(osc.block(48_000))
    assert abs(peak_hz - 800.0) <= 1.0


def test_am_mode_keeps_the_carrier_and_adds_sidebands_at_the_am_rate():
    osc = Oscillator(RATE, Perceptual("am", corner_hz=800.0, am_hz=250.0))
    osc.set_target(0.8, 1200.0)
    osc.block(64)
    x = osc.block(48_000)
    window = np.hanning(x.size)
    amplitude = 2 * np.abs(np.fft.rfft(x * window)) / window.sum()  # 1 Hz bins
    # (0.5 − 0.5·cos)·sin: half the level on the carrier, a quarter on each sideband
    assert amplitude[1200] == pytest.approx(0.4, rel=0.01)
    assert amplitude[950] == pytest.approx(0.2, rel=0.01)
    assert amplitude[1450] == pytest.approx(0.2, rel=0.01)
    elsewhere = np.ones(amplitude.size, bool)
    for k in (950, 1200, 1450):
        elsewhere[k - 2:k + 3] = False
    assert np.max(amplitude[elsewhere]) < 0.01
    # envelope: a raised cosine from 0 to the full level
    assert np.max(np.abs(x)) == pytest.approx(0.8, rel=0.02)
    below = Oscillator(RATE, Perceptual("am"))  # below the corner: plain carrier
    below.set_target(0.8, 600.0)
    below.block(64)
    assert sorted(np.argsort(np.abs(np.fft.rfft(below.block(48_000))))[-1:]) == [600]


def test_carrier_never_aliases():
    osc = Oscillator(RATE)
    osc.set_target(1.0, 30_000.0)
    osc.block(64)
    peak_hz, _ = _spectrum_peak(osc.block(48_000))
    assert abs(peak_hz - MAX_CARRIER_FRACTION * RATE) <= 1.0


def test_kernel_is_compiled_and_keeps_phase():
    out = np.empty(48, dtype=np.float32)
    phase, am_phase = fill_block(out, RATE, 0.0, 1000.0, 1000.0, 1.0, 1.0, 0.0, 250.0, 0.0, 0.0)
    assert phase == pytest.approx(0.0, abs=1e-9)  # 48 samples of 1 kHz = one period
    assert am_phase == pytest.approx(0.25)
    assert hasattr(fill_block, "signatures") and fill_block.signatures


@pytest.mark.parametrize("bad", [dict(mode="loud"), dict(corner_hz=0.0),
                                 dict(am_hz=math.nan)])
def test_perceptual_rejects_bad_settings(bad):
    with pytest.raises(ValueError):
        Perceptual(**bad)


def test_oscillator_rejects_bad_targets():
    osc = Oscillator(RATE)
    for level, hz in ((math.nan, 100.0), (0.5, -1.0), (0.5, math.inf)):
        with pytest.raises(ValueError):
            osc.set_target(level, hz)


@given(st.floats(0.01, 100.0), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3))
def test_amplitude_map_is_clamped_and_monotone(full_scale, a, b):
    amap = AmplitudeMap(full_scale)
    la, lb = amap.level(a), amap.level(b)
    assert 0.0 <= la <= 1.0 and 0.0 <= lb <= 1.0
    if a <= b:
        assert la <= lb
    if 0.0 <= a <= full_scale:
        assert la == pytest.approx(a / full_scale)


@pytest.mark.parametrize("full_scale", [0.0, -1.0, math.nan, math.inf])
def test_amplitude_map_rejects_bad_full_scale(full_scale):
    with pytest.raises(ValueError):
        AmplitudeMap(full_scale)
