from __future__ import annotations

import math

import pytest

from burrforce.server.model import VibrationParams, vibration


def test_free_spinning_amplitude_at_the_spindle_frequency():
    amp, freq = vibration(60000.0, 1.2, True, VibrationParams(fd_N=0.4, g=0.0))
    assert amp == pytest.approx(0.4) and freq == pytest.approx(1000.0)


def test_burring_gain_adds_in_quadrature_and_sign_of_rpm_is_ignored():
    amp, freq = vibration(-30000.0, -2.0, True, VibrationParams(fd_N=0.3, g=0.2))
    assert amp == pytest.approx(math.sqrt(0.3**2 + 0.4**2))
    assert freq == pytest.approx(500.0)


def test_harmonic_for_fluted_burrs():
    _amp, freq = vibration(60000.0, 0.0, True, VibrationParams(harmonic=6.0))
    assert freq == pytest.approx(6000.0)


@pytest.mark.parametrize(("rpm", "on"), [(60000.0, False), (0.0, True), (float("nan"), True)])
def test_zero_when_the_spindle_is_off(rpm, on):
    assert vibration(rpm, 5.0, on, VibrationParams(fd_N=1.0, g=1.0)) == (0.0, 0.0)


@pytest.mark.parametrize("kwargs", [{"fd_N": -0.1}, {"g": float("inf")}, {"harmonic": 0.0}])
def test_bad_vibration_parameters_are_refused(kwargs):
    with pytest.raises(ValueError):
        VibrationParams(**kwargs)
