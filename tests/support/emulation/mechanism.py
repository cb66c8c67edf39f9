"""The emulated Falcon's mechanism: the grip as a point mass moved by the motors and a hand.

Physics (SI units: m, m/s, N, kg, N·m), integrated in real time between I/O cycles:

- the end effector is a point mass (the ``falcon`` profile's ``sim_mass_kg`` plus the sim
  device's ``GRIP_KG`` hand grip) with viscous friction (the profile's
  ``sim_damping_N_s_mm``);
- the motors hold the torques of the last command (τ = −command/10000 N·m, a zero-order
  hold); they push the grip with F = (dθ/dp)ᵀ·τ evaluated at the current position
  (``falcon.kinematics``), so a driver's force → command conversion is checked against the
  real kinematics;
- a scripted hand: a spring-damper (the sim device's 0.3 N/mm, 0.003 N·s/mm by default)
  pulling toward a piecewise-linear path of waypoints, or released (no hand force);
- end stops: a stiff spring-damper wall on a sphere of ``WORKSPACE_RADIUS_M`` around the
  workspace centre, so the grip never leaves where the kinematics is valid;
- semi-implicit Euler in substeps of at most the sim device's ``MAX_SUBSTEP_S``.

The encoders read IK(true position), quantized to counts (``angle_to_encoder``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from burrforce.server.devices.falcon.kinematics import (
    WORKSPACE_CENTRE_M,
    WORKSPACE_RADIUS_M,
    angle_to_encoder,
    commands_to_torques,
    end_effector_force,
    inverse_kinematics,
)
from burrforce.server.devices.sim import GRIP_KG, HAND_B_N_S_MM, HAND_K_N_MM, MAX_SUBSTEP_S
from burrforce.server.haptics.profiles import PROFILES

STOP_STIFFNESS_N_M = 200_000.0
STOP_DAMPING_N_S_M = 200.0
#: Longest stretch integrated in one call (s): a longer idle gap only needs the last part
#: (the hand has long settled the grip by then).
MAX_SPAN_S = 10.0
#: The hand may aim beyond the end stops (pushing the grip against them), up to this far (mm).
HAND_REACH_MM = 100.0


@njit(cache=True, nogil=True)
def _hand_target(path_t: np.ndarray, path_p: np.ndarray, t: float,
                 target: np.ndarray, target_v: np.ndarray) -> None:
    """Position and velocity of a piecewise-linear path (times (n,), s; points (n, 3), m)
    at ``t`` (s); held at the ends."""
    n = path_t.shape[0]
    if t <= path_t[0] or n == 1:
        target[:] = path_p[0]
        target_v[:] = 0.0
        return
    if t >= path_t[n - 1]:
        target[:] = path_p[n - 1]
        target_v[:] = 0.0
        return
    k = 1
    while path_t[k] < t:
        k += 1
    span = path_t[k] - path_t[k - 1]
    s = (t - path_t[k - 1]) / span
    for i in range(3):
        target[i] = path_p[k - 1, i] + s * (path_p[k, i] - path_p[k - 1, i])
        target_v[i] = (path_p[k, i] - path_p[k - 1, i]) / span


@njit(cache=True, nogil=True)
def integrate(p: np.ndarray, v: np.ndarray, tau: np.ndarray, t0_s: float, span_s: float,
              path_t: np.ndarray, path_p: np.ndarray, hand_on: bool, hand_k: float,
              hand_b: float, mass: float, friction: float, centre: np.ndarray,
              stop_radius: float, max_substep: float) -> None:
    """Advance ``p`` (m, (3,)) and ``v`` (m/s, (3,)) in place over ``span_s`` seconds under
    motor torques ``tau`` (N·m, (3,)) and the hand (path time ``t0_s`` at the start)."""
    if span_s <= 0.0:
        return
    n = max(1, math.ceil(span_s / max_substep - 1e-9))
    h = span_s / n
    target = np.empty(3)
    target_v = np.empty(3)
    force = np.zeros(3)
    for step in range(n):
        motor = end_effector_force(p, tau)
        for i in range(3):
            force[i] = motor[i] if math.isfinite(motor[i]) else 0.0
            force[i] -= friction * v[i]
        if hand_on:
            _hand_target(path_t, path_p, t0_s + step * h, target, target_v)
            for i in range(3):
                force[i] += hand_k * (target[i] - p[i]) + hand_b * (target_v[i] - v[i])
        r2 = 0.0
        for i in range(3):
            r2 += (p[i] - centre[i]) ** 2
        r = math.sqrt(r2)
        if r > stop_radius:
            v_out = 0.0
            for i in range(3):
                v_out += v[i] * (p[i] - centre[i]) / r
            push = STOP_STIFFNESS_N_M * (r - stop_radius) + STOP_DAMPING_N_S_M * max(v_out, 0.0)
            for i in range(3):
                force[i] -= push * (p[i] - centre[i]) / r
        for i in range(3):
            v[i] += force[i] / mass * h
            p[i] += v[i] * h


def warm_up() -> None:
    """Compile the numba kernels now (seconds with a cold cache), not in the first I/O cycle
    where the host's driver would time out waiting."""
    m = FalconMechanism(0)
    m.command(1_000_000, (100, 100, 100))
    m.advance(2_000_000)
    m.encoder_counts()
    m.motor_force_N()


class FalconMechanism:
    """The grip, the motors' held torques and the hand, advanced in real time.

    Positions given and reported by the ``*_mm`` methods are mm relative to
    :data:`WORKSPACE_CENTRE_M` in the kinematics frame (the frame ``falcon.kinematics``
    uses); ``p``/``v`` hold the absolute state in m, m/s.
    """

    def __init__(self, t_ns: int, start_mm=(0.0, 0.0, 0.0), hand_k_N_mm: float = HAND_K_N_MM,
                 hand_b_N_s_mm: float = HAND_B_N_S_MM, hand_on: bool = True) -> None:
        profile = PROFILES["falcon"]
        self.mass_kg = profile.sim_mass_kg + GRIP_KG
        self.friction_N_s_m = profile.sim_damping_N_s_mm * 1e3
        self.centre = np.array(WORKSPACE_CENTRE_M, dtype=float)
        self.stop_radius_m = float(WORKSPACE_RADIUS_M)
        self.p = self.centre + self._offset_m(start_mm, self.stop_radius_m * 1e3)
        self.v = np.zeros(3)
        self.tau = np.zeros(3)
        self.t_ns = t_ns
        self.hand_on = bool(hand_on)
        self.hand_k = 0.0
        self.hand_b = 0.0
        self.set_hand_gains(hand_k_N_mm, hand_b_N_s_mm)
        self.path_t = np.zeros(1)
        self.path_p = self.p.reshape(1, 3).copy()
        self.path_t0_ns = t_ns

    def _offset_m(self, position_mm, limit_mm: float) -> np.ndarray:
        offset = np.asarray(position_mm, dtype=float).reshape(-1) * 1e-3
        if offset.shape != (3,) or not np.all(np.isfinite(offset)):
            raise ValueError(f"a position is 3 finite numbers (mm), got {position_mm!r}")
        if np.linalg.norm(offset) * 1e3 > limit_mm:
            raise ValueError(f"position {offset.tolist()} m from the centre is farther than "
                             f"{limit_mm:.0f} mm")
        return offset

    def set_hand_gains(self, k_N_mm: float, b_N_s_mm: float) -> None:
        if not (math.isfinite(k_N_mm) and math.isfinite(b_N_s_mm)) or k_N_mm < 0 \
                or b_N_s_mm < 0 or k_N_mm > 5.0:
            raise ValueError(f"hand stiffness must be 0..5 N/mm and damping ≥ 0, got "
                             f"{k_N_mm}, {b_N_s_mm}")
        self.hand_k = k_N_mm * 1e3
        self.hand_b = b_N_s_mm * 1e3

    def advance(self, now_ns: int) -> None:
        """Integrate from the last time to ``now_ns`` under the held torques."""
        span = (now_ns - self.t_ns) * 1e-9
        if span <= 0.0:
            return
        skipped = max(0.0, span - MAX_SPAN_S)
        t0 = (self.t_ns - self.path_t0_ns) * 1e-9 + skipped
        integrate(self.p, self.v, self.tau, t0, span - skipped, self.path_t, self.path_p,
                  self.hand_on, self.hand_k, self.hand_b, self.mass_kg, self.friction_N_s_m,
                  self.centre, self.stop_radius_m, MAX_SUBSTEP_S)
        self.t_ns = now_ns

    def command(self, now_ns: int, motor: tuple[int, int, int]) -> None:
        """Advance to ``now_ns``, then hold the torques of motor ``motor`` commands."""
        self.advance(now_ns)
        self.tau = commands_to_torques(np.asarray(motor, dtype=float))

    def set_path(self, now_ns: int, waypoints: list[tuple[float, list[float]]]) -> None:
        """Hand path from ``now_ns``: (time s ≥ 0, increasing; position mm) waypoints."""
        if not waypoints:
            raise ValueError("a hand path needs at least one waypoint")
        times = np.array([float(t) for t, _ in waypoints])
        if not np.all(np.isfinite(times)) or times[0] < 0 or np.any(np.diff(times) <= 0):
            raise ValueError(f"waypoint times must be finite, ≥ 0 and increasing, got "
                             f"{times.tolist()}")
        points = np.array([self.centre + self._offset_m(p, HAND_REACH_MM) for _, p in waypoints])
        self.advance(now_ns)
        self.path_t, self.path_p, self.path_t0_ns = times, points, now_ns
        self.hand_on = True

    def release_hand(self, now_ns: int) -> None:
        self.advance(now_ns)
        self.hand_on = False

    def place(self, now_ns: int, position_mm) -> None:
        """Put the grip at ``position_mm`` at rest (the hand keeps its path)."""
        self.advance(now_ns)
        self.p[:] = self.centre + self._offset_m(position_mm, self.stop_radius_m * 1e3)
        self.v[:] = 0.0

    def encoder_counts(self) -> np.ndarray:
        """True encoder counts ((3,), int64) at the current position."""
        counts = np.rint(angle_to_encoder(inverse_kinematics(self.p)))
        if not np.all(np.isfinite(counts)):   # pragma: no cover - the stops prevent it
            raise RuntimeError(f"grip out of the mechanism's reach at {self.p.tolist()} m")
        return counts.astype(np.int64)

    def motor_force_N(self) -> np.ndarray:
        """The force (N, (3,)) the held torques exert at the current position."""
        return end_effector_force(self.p, self.tau)

    def position_mm(self) -> np.ndarray:
        return (self.p - self.centre) * 1e3

    def hand_target_mm(self, now_ns: int) -> list[float] | None:
        if not self.hand_on:
            return None
        target, target_v = np.empty(3), np.empty(3)
        _hand_target(self.path_t, self.path_p, (now_ns - self.path_t0_ns) * 1e-9, target,
                     target_v)
        return ((target - self.centre) * 1e3).tolist()
