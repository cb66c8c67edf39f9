"""The Falcon's kinematics: round trips over the workspace, the Jacobian against finite
differences, force ↔ torque ↔ command."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from burrforce.server.devices.falcon import kinematics as K

unit = st.floats(-1.0, 1.0, allow_nan=False)


@st.composite
def workspace_points(draw, radius_m: float = K.WORKSPACE_RADIUS_M) -> np.ndarray:
    """A point in the ball of ``radius_m`` around the workspace centre."""
    v = np.array([draw(unit), draw(unit), draw(unit)])
    n = float(np.linalg.norm(v))
    if n > 1.0:
        v /= n
    return K.WORKSPACE_CENTRE_M + radius_m * v


forces = st.tuples(*(st.floats(-10.0, 10.0, allow_nan=False),) * 3).map(np.array)


def _fd_jacobian(p: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = [(K.inverse_kinematics(p + h * e) - K.inverse_kinematics(p - h * e)) / (2 * h)
            for e in np.eye(3)]
    return np.array(cols).T


def test_inverse_kinematics_is_valid_and_well_conditioned_on_the_workspace_sphere():
    rng = np.random.default_rng(7)
    dirs = rng.normal(size=(4000, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    for d in dirs:
        p = K.WORKSPACE_CENTRE_M + K.WORKSPACE_RADIUS_M * d
        jac = K.angle_jacobian(p)
        assert np.all(np.isfinite(K.inverse_kinematics(p))), p
        assert np.linalg.cond(jac) < 5.0, p


def test_centre_is_symmetric_and_sensible():
    theta = K.inverse_kinematics(K.WORKSPACE_CENTRE_M)
    assert np.allclose(theta, theta[0])
    assert -math.pi / 2 < theta[0] < math.pi / 2
    # Out of reach: NaN, not a wrong number.
    assert np.all(np.isnan(K.inverse_kinematics(np.array([0.0, 0.0, 0.3]))))
    assert np.all(np.isnan(K.angle_jacobian(np.array([0.0, 0.0, 0.3]))))


@given(workspace_points())
def test_jacobian_matches_finite_differences(p):
    jac = K.angle_jacobian(p)
    assert np.allclose(jac, _fd_jacobian(p), rtol=1e-5, atol=1e-5 * np.abs(jac).max())


@given(workspace_points(), workspace_points(radius_m=1.5 * K.WORKSPACE_RADIUS_M))
def test_forward_kinematics_inverts_inverse_kinematics(p, guess):
    # The guess may be anywhere around the workspace, even out of reach.
    theta = K.inverse_kinematics(p)
    q, ok = K.forward_kinematics(theta, guess)
    assert ok
    assert np.abs(q - p).max() < 1e-9  # 1 nm; measured worst ~1e-11 m


def test_forward_kinematics_tolerates_absurd_guesses_and_reports_failure():
    p = K.WORKSPACE_CENTRE_M + np.array([0.01, -0.02, 0.015])
    theta = K.inverse_kinematics(p)
    for guess in ([1.0, 2.0, 3.0], [math.nan, 0.0, 0.0], [0.0, 0.0, -1.0]):
        q, ok = K.forward_kinematics(theta, np.array(guess))
        assert ok and np.abs(q - p).max() < 1e-9
    # Angles no position produces: not converged, and the position stays finite.
    q, ok = K.forward_kinematics(np.array([3.0, -3.0, 3.0]), K.WORKSPACE_CENTRE_M)
    assert not ok and np.all(np.isfinite(q))
    q, ok = K.forward_kinematics(np.array([math.nan, 0.0, 0.0]), K.WORKSPACE_CENTRE_M)
    assert not ok


@given(workspace_points(), forces)
def test_force_torque_round_trip(p, force):
    tau = K.motor_torques(p, force)
    assert np.allclose(K.end_effector_force(p, tau), force, atol=1e-9)


@given(workspace_points(), forces, workspace_points(radius_m=0.005))
def test_torques_do_the_virtual_work_of_the_force(p, force, dp_around_centre):
    # τ·dθ = F·dp for a small displacement dp.
    dp = (dp_around_centre - K.WORKSPACE_CENTRE_M) * 1e-3
    # A displacement the angles can resolve: below ~1 nm, IK(p ± dp) differ by little more
    # than their own round-off (~2e-16 rad), and the difference measures that, not the
    # Jacobian (hypothesis found |dp| ~ 1e-15 m: 1.2e-15 J of round-off in 1.0e-14 J).
    assume(np.linalg.norm(dp) >= 1e-9)
    dtheta = K.inverse_kinematics(p + dp) - K.inverse_kinematics(p - dp)
    work_joint = float(K.motor_torques(p, force) @ dtheta)
    work_cart = float(force @ (2 * dp))
    # Within 1e-4 of the work's scale |F|·|2dp|: the central difference's O(dp³) remainder
    # does not vanish when F ⊥ dp makes the work itself 0 (hypothesis found −1.0e-12 there
    # against a bare 1e-12 floor in CI).
    scale = float(np.linalg.norm(force) * np.linalg.norm(2 * dp))
    assert abs(work_joint - work_cart) <= 1e-4 * max(abs(work_cart), scale) + 1e-15


def test_five_newtons_up_at_the_centre():
    tau = K.motor_torques(K.WORKSPACE_CENTRE_M, np.array([0.0, 0.0, 5.0]))
    cmd = K.torques_to_commands(tau)
    assert np.all(cmd == cmd[0]) and 500 < abs(cmd[0]) < 3000


@given(st.tuples(*(st.floats(-1e6, 1e6, allow_nan=False),) * 3).map(np.array))
def test_commands_are_int16_and_keep_the_torque_direction(tau):
    cmd = K.torques_to_commands(tau)
    assert cmd.dtype == np.int64
    assert np.all(cmd >= -32768) and np.all(cmd <= 32767)
    back = K.commands_to_torques(cmd)
    largest = np.abs(tau).max()
    if largest <= K.MAX_TORQUE_NM:
        assert np.allclose(back, tau, atol=0.5 / K.COMMANDS_PER_NM)
    else:
        # Scaled as a whole: parallel to tau, the largest component at the limit.
        assert np.abs(back).max() == pytest.approx(K.MAX_TORQUE_NM, abs=1e-4)
        assert np.allclose(back * largest / np.abs(back).max(), tau,
                           atol=largest * 1e-4 + 1e-3)


def test_non_finite_torque_gives_zero_commands():
    for bad in ([math.nan, 0.0, 0.0], [math.inf, 1.0, 1.0]):
        assert np.array_equal(K.torques_to_commands(np.array(bad)), [0, 0, 0])


def test_commands_to_torques_inverts_the_scaling():
    assert np.allclose(K.commands_to_torques(np.array([10000, -20000, 0])), [-1.0, 2.0, 0.0])


@given(st.tuples(*(st.integers(-32768, 32767),) * 3).map(np.array))
def test_encoder_angle_round_trip(enc):
    theta = K.encoder_to_angle(enc)
    assert np.array_equal(np.round(K.angle_to_encoder(theta)), enc)


def test_encoder_scale():
    assert math.degrees(K.RAD_PER_COUNT) == pytest.approx(0.036434, rel=1e-4)
    assert np.allclose(K.encoder_to_angle(np.zeros(3)), math.radians(35.0))
