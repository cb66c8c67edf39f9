"""Kinematics of the Novint Falcon (a delta robot): encoder counts ↔ motor angles, inverse and
forward kinematics, the Jacobian, and force ↔ motor torque ↔ motor command.

The model is R. E. Stamper's (PhD thesis 97-4, University of Maryland) with the Falcon's
geometry as libnifalcon measured it (BSD-3, (c) 2007-2009 Nonpolynomial Labs/Kyle Machulis;
constants from ``include/falcon/core/FalconGeometry.h``). The equations are re-derived here;
the Jacobian is the exact derivative of *this* inverse kinematics (libnifalcon's z column uses
sin²θ2 where the derivative has sinθ2·sinθ3, which makes vertical forces ~1.3× too strong).

Frame and units: positions in **metres** in the Falcon's own frame as libnifalcon uses it
(z points away from the device body towards the user; the grip rests near
:data:`WORKSPACE_CENTRE_M`), angles in radians, forces in N, torques in N·m. All kernels are
numba ``@njit(cache=True, nogil=True)`` on float64 arrays.

Each leg i sits at azimuth φ_i. In the leg's frame (u, v, w) = R(φ_i)·p − (r, s, 0), with
θ1 the motor (upper arm) angle, θ3 the parallelogram's out-of-plane angle, θ2 its in-plane
angle and K = d + e + b·sinθ3, the leg reaches::

    u = a·cosθ1 − c + K·cosθ2,   v = b·cosθ3 − f,   w = a·sinθ1 + K·sinθ2
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Geometry (m): Stamper's lengths for the Falcon, per libnifalcon's measurements.
A_M = 0.060       # motor axis to knee (upper arm)
B_M = 0.1025      # parallelogram side (lower arm)
C_M = 0.01443     # lower-arm attachment to end-effector centre, u component
D_M = 0.01125     # lower arm to end-effector joint
E_M = 0.01125     # knee to lower-arm joint
F_M = -0.025      # lower-arm attachment to end-effector centre, v component
R_M = 0.0400      # frame origin to leg base, u component
S_M = -0.02309    # frame origin to leg base, v component
#: Leg azimuths (rad): 120° apart, turned 15° from the desk plane.
PHI_RAD = np.array([math.pi / 2, -math.pi / 6, -5 * math.pi / 6]) + math.pi / 12

# Encoder → motor angle: a 320-slot wheel read in quadrature on the motor shaft (diameter
# 14.25 mm) drives the arm's capstan drum (diameter 110 mm); count 0 ≈ 35°.
ENCODER_COUNTS_PER_REV = 320 * 4
SHAFT_DIAMETER_M = 0.01425
DRUM_DIAMETER_M = 0.110
RAD_PER_COUNT = 2.0 * math.pi * SHAFT_DIAMETER_M / (ENCODER_COUNTS_PER_REV * DRUM_DIAMETER_M)
ANGLE_AT_ZERO_COUNT_RAD = math.radians(35.0)

# Motor command scaling (libnifalcon's getForces): command = −torque·10000, int16 on the wire.
COMMANDS_PER_NM = 10000.0
INT16_MAX = 32767
#: libnifalcon scales all three torques down together when one exceeds 30 N·m, but 30 N·m is
#: 300 000 counts: far beyond int16. We scale to the largest torque the wire can carry, so
#: saturation shortens the force but never turns it.
MAX_TORQUE_NM = INT16_MAX / COMMANDS_PER_NM

#: Where the grip rests in the middle of its travel (m, Falcon frame).
WORKSPACE_CENTRE_M = np.array([0.0, 0.0, 0.11])
#: Radius (m) of a sphere around WORKSPACE_CENTRE_M on which the inverse kinematics is valid
#: and well conditioned (checked by ``tests/test_falcon_kinematics.py``). The mechanism's
#: practical travel is a ~±50 mm box; this sphere is a conservative inner bound.
WORKSPACE_RADIUS_M = 0.04

#: Forward kinematics stops when the angle residual is below this (rad); with |dp/dθ| ≲ 0.1
#: m/rad in the workspace that is a position error ≲ 1e-11 m.
FK_TOLERANCE_RAD = 1e-10
FK_MAX_ITERATIONS = 40


@njit(cache=True, nogil=True)
def encoder_to_angle(enc: np.ndarray) -> np.ndarray:
    """Motor angles (rad, (3,)) from encoder counts ((3,), any real dtype)."""
    out = np.empty(3)
    for i in range(3):
        out[i] = enc[i] * RAD_PER_COUNT + ANGLE_AT_ZERO_COUNT_RAD
    return out


@njit(cache=True, nogil=True)
def angle_to_encoder(theta: np.ndarray) -> np.ndarray:
    """Encoder counts ((3,), float: round outside) at motor angles ``theta`` (rad, (3,))."""
    out = np.empty(3)
    for i in range(3):
        out[i] = (theta[i] - ANGLE_AT_ZERO_COUNT_RAD) / RAD_PER_COUNT
    return out


@njit(cache=True, nogil=True)
def _leg_frame(p: np.ndarray, leg: int) -> tuple[float, float, float]:
    cphi = math.cos(PHI_RAD[leg])
    sphi = math.sin(PHI_RAD[leg])
    u = cphi * p[0] + sphi * p[1] - R_M
    v = -sphi * p[0] + cphi * p[1] - S_M
    return u, v, p[2]


@njit(cache=True, nogil=True)
def _leg_angles(p: np.ndarray, leg: int) -> tuple[float, float, float]:
    """(θ1, θ2, θ3) of one leg at position ``p`` (m); NaN when out of reach."""
    u, v, w = _leg_frame(p, leg)
    cos3 = (v + F_M) / B_M
    if not -1.0 <= cos3 <= 1.0:
        return math.nan, math.nan, math.nan
    theta3 = math.acos(cos3)
    k = D_M + E_M + B_M * math.sin(theta3)
    # (u + c − a·cosθ1)² + (w − a·sinθ1)² = K²; with t = tan(θ1/2): q2·t² + q1·t + q0 = 0.
    uc = u + C_M
    base = uc * uc + w * w + A_M * A_M - k * k
    q0 = base - 2.0 * A_M * uc
    q1 = -4.0 * A_M * w
    q2 = base + 2.0 * A_M * uc
    disc = q1 * q1 - 4.0 * q0 * q2
    if disc < 0.0 or q2 == 0.0:
        return math.nan, math.nan, math.nan
    # The elbow-out branch is the Falcon's; the other root folds the arm through the base.
    t = (-q1 - math.sqrt(disc)) / (2.0 * q2)
    theta1 = 2.0 * math.atan(t)
    cos2 = (uc - A_M * math.cos(theta1)) / k
    if not -1.0 <= cos2 <= 1.0:
        return math.nan, math.nan, math.nan
    return theta1, math.acos(cos2), theta3


@njit(cache=True, nogil=True)
def _ik_into(p: np.ndarray, theta: np.ndarray) -> bool:
    ok = True
    for leg in range(3):
        t1, _, _ = _leg_angles(p, leg)
        theta[leg] = t1
        ok = ok and math.isfinite(t1)
    return ok


@njit(cache=True, nogil=True)
def inverse_kinematics(p_m: np.ndarray) -> np.ndarray:
    """Motor angles θ1 (rad, (3,)) that put the end effector at ``p_m`` (m, (3,)); NaN for a
    leg that cannot reach it."""
    theta = np.empty(3)
    _ik_into(p_m, theta)
    return theta


@njit(cache=True, nogil=True)
def _jacobian_into(p: np.ndarray, jac: np.ndarray) -> bool:
    for leg in range(3):
        t1, t2, t3 = _leg_angles(p, leg)
        if not math.isfinite(t1):
            return False
        s3 = math.sin(t3)
        # Implicit derivative of the leg's closure (u+c−a·cosθ1)² + (w−a·sinθ1)² = K(v)²:
        # dθ1/d(u, v, w) = (cosθ2·sinθ3, cosθ3, sinθ2·sinθ3) / (−a·sinθ3·sin(θ1 − θ2)).
        den = -A_M * s3 * math.sin(t1 - t2)
        if den == 0.0:
            return False
        du = math.cos(t2) * s3 / den
        dv = math.cos(t3) / den
        dw = math.sin(t2) * s3 / den
        cphi = math.cos(PHI_RAD[leg])
        sphi = math.sin(PHI_RAD[leg])
        jac[leg, 0] = du * cphi - dv * sphi
        jac[leg, 1] = du * sphi + dv * cphi
        jac[leg, 2] = dw
    return True


@njit(cache=True, nogil=True)
def angle_jacobian(p_m: np.ndarray) -> np.ndarray:
    """dθ/dp ((3, 3), rad/m; row i = leg i) at ``p_m`` (m, (3,)); NaN where out of reach."""
    jac = np.empty((3, 3))
    if not _jacobian_into(p_m, jac):
        jac[:, :] = math.nan
    return jac


@njit(cache=True, nogil=True)
def _solve3(m: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """out = m⁻¹·b by Cramer's rule (3×3); False when m is singular."""
    c00 = m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1]
    c01 = m[1, 2] * m[2, 0] - m[1, 0] * m[2, 2]
    c02 = m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0]
    det = m[0, 0] * c00 + m[0, 1] * c01 + m[0, 2] * c02
    if det == 0.0 or not math.isfinite(det):
        return False
    inv = 1.0 / det
    i00 = c00 * inv
    i01 = (m[0, 2] * m[2, 1] - m[0, 1] * m[2, 2]) * inv
    i02 = (m[0, 1] * m[1, 2] - m[0, 2] * m[1, 1]) * inv
    i10 = c01 * inv
    i11 = (m[0, 0] * m[2, 2] - m[0, 2] * m[2, 0]) * inv
    i12 = (m[0, 2] * m[1, 0] - m[0, 0] * m[1, 2]) * inv
    i20 = c02 * inv
    i21 = (m[0, 1] * m[2, 0] - m[0, 0] * m[2, 1]) * inv
    i22 = (m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]) * inv
    out[0] = i00 * b[0] + i01 * b[1] + i02 * b[2]
    out[1] = i10 * b[0] + i11 * b[1] + i12 * b[2]
    out[2] = i20 * b[0] + i21 * b[1] + i22 * b[2]
    return True


@njit(cache=True, nogil=True)
def _residual_norm(theta_target: np.ndarray, theta: np.ndarray) -> float:
    s = 0.0
    for i in range(3):
        d = theta_target[i] - theta[i]
        s += d * d
    return math.sqrt(s)


@njit(cache=True, nogil=True)
def forward_kinematics(theta: np.ndarray, guess_m: np.ndarray) -> tuple[np.ndarray, bool]:
    """(end-effector position (m, (3,)), converged) at motor angles ``theta`` (rad, (3,)).

    Newton's method on the inverse kinematics, seeded by ``guess_m`` (m, (3,); the last
    position), with step halving whenever a step does not reduce the angle residual or leaves
    the reachable set. A guess out of reach restarts from :data:`WORKSPACE_CENTRE_M`.
    Converged means the residual ‖θ − IK(p)‖ fell below :data:`FK_TOLERANCE_RAD` (a position
    error ≲ 1e-11 m); otherwise the best position found is returned with False.
    """
    p = np.empty(3)
    trial = np.empty(3)
    th = np.empty(3)
    diff = np.empty(3)
    step = np.empty(3)
    jac = np.empty((3, 3))
    for i in range(3):
        p[i] = guess_m[i]
        if not math.isfinite(p[i]):
            p[:] = WORKSPACE_CENTRE_M
            break
    if not math.isfinite(theta[0] + theta[1] + theta[2]):
        return p, False
    if not _ik_into(p, th):
        p[:] = WORKSPACE_CENTRE_M
        if not _ik_into(p, th):  # pragma: no cover - the centre is always reachable
            return p, False
    err = _residual_norm(theta, th)
    for _ in range(FK_MAX_ITERATIONS):
        if err < FK_TOLERANCE_RAD:
            return p, True
        if not _jacobian_into(p, jac):
            return p, False
        for i in range(3):
            diff[i] = theta[i] - th[i]
        if not _solve3(jac, diff, step):
            return p, False
        scale = 1.0
        improved = False
        for _half in range(30):
            for i in range(3):
                trial[i] = p[i] + scale * step[i]
            if _ik_into(trial, th):
                trial_err = _residual_norm(theta, th)
                if trial_err < err:
                    p[:] = trial
                    err = trial_err
                    improved = True
                    break
            scale *= 0.5
        if not improved:
            # No step along Newton's direction helps: as close as float64 gets here.
            _ik_into(p, th)
            return p, err < FK_TOLERANCE_RAD * 100.0
    return p, err < FK_TOLERANCE_RAD


@njit(cache=True, nogil=True)
def motor_torques(p_m: np.ndarray, force_N: np.ndarray) -> np.ndarray:
    """Motor torques (N·m, (3,)) that push the end effector at ``p_m`` (m, (3,)) with
    ``force_N`` (N, (3,)). Virtual work: τ = (dp/dθ)ᵀ·F, i.e. solve (dθ/dp)ᵀ·τ = F.
    NaN when ``p_m`` is out of reach or singular."""
    jac = np.empty((3, 3))
    tau = np.empty(3)
    if not _jacobian_into(p_m, jac) or not _solve3(jac.T.copy(), force_N, tau):
        tau[:] = math.nan
    return tau


@njit(cache=True, nogil=True)
def end_effector_force(p_m: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """The force (N, (3,)) the end effector at ``p_m`` (m, (3,)) exerts under motor torques
    ``tau`` (N·m, (3,)): F = (dθ/dp)ᵀ·τ (the inverse of :func:`motor_torques`)."""
    jac = np.empty((3, 3))
    force = np.empty(3)
    if not _jacobian_into(p_m, jac):
        force[:] = math.nan
        return force
    for j in range(3):
        force[j] = jac[0, j] * tau[0] + jac[1, j] * tau[1] + jac[2, j] * tau[2]
    return force


@njit(cache=True, nogil=True)
def torques_to_commands(tau: np.ndarray) -> np.ndarray:
    """int16 motor commands ((3,), int64 dtype) for torques ``tau`` (N·m, (3,)).

    command = −τ·COMMANDS_PER_NM. When a torque exceeds :data:`MAX_TORQUE_NM` all three are
    scaled down together (the force keeps its direction); the result is clamped to int16.
    A non-finite torque gives all-zero commands."""
    out = np.zeros(3, dtype=np.int64)
    largest = 0.0
    for i in range(3):
        if not math.isfinite(tau[i]):
            return out
        largest = max(largest, abs(tau[i]))
    scale = 1.0
    if largest > MAX_TORQUE_NM:
        scale = MAX_TORQUE_NM / largest
    for i in range(3):
        c = round(-tau[i] * scale * COMMANDS_PER_NM)
        out[i] = min(max(c, -INT16_MAX - 1), INT16_MAX)
    return out


@njit(cache=True, nogil=True)
def commands_to_torques(cmd: np.ndarray) -> np.ndarray:
    """Motor torques (N·m, (3,)) a motor command ((3,), int16 values) asks for: −cmd/10000."""
    out = np.empty(3)
    for i in range(3):
        out[i] = -cmd[i] / COMMANDS_PER_NM
    return out
