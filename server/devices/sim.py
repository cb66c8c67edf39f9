"""A simulated haptic device: a point mass with viscous friction, encoder quantization and a
scripted hand, for CI, benchmarks and trying burrforce without hardware.

The physics is the one ``burrforce bench stability`` closes its loop around (the bench steps
:class:`SimMechanism` in simulated time; :class:`SimDevice` steps it in real time for the
device loop):

- the end effector is a mass (the profile's ``sim_mass_kg`` plus a 0.1 kg grip) with viscous
  friction ``sim_damping_N_s_mm``, integrated by semi-implicit Euler in substeps of at most
  0.1 ms under a force held constant over each substep (a servo loop's zero-order hold);
- the hand is a spring-damper (0.3 N/mm, 0.003 N·s/mm) pulling it toward a target that a
  script moves;
- the encoder quantizes each axis to the profile's ``resolution_mm``; the velocity the device
  reports is estimated from those readings (:class:`DeviceVelocity`), as a driver must.

Units: mm, s, N (mass N·s²/mm = kg/1000, stiffness N/mm, damping N·s/mm), energy N·mm = mJ.
"""

from __future__ import annotations

import inspect
import math
import time
from collections.abc import Callable

import numpy as np

from ..haptics.profiles import PROFILES, DeviceProfile
from ..haptics.velocity import DeviceVelocity
from .base import DeviceInfo, DeviceState, HapticDevice, clamp_force

HAND_K_N_MM = 0.3
HAND_B_N_S_MM = 0.003
GRIP_KG = 0.1
MAX_SUBSTEP_S = 1e-4

#: A hand script: time since start (s) → target position (3,) and velocity (3,), mm and mm/s,
#: in the device frame.
HandScript = Callable[[float], tuple[tuple[float, float, float], tuple[float, float, float]]]


class SimMechanism:
    """The simulated end effector and hand. ``x``, ``v``: true position and velocity (mm,
    mm/s, lists of 3 floats); ``work_mJ``: ∫ F_applied·v dt so far (energy the rendered
    force put in)."""

    def __init__(self, profile: DeviceProfile, start_mm=(0.0, 0.0, 0.0),
                 hand_k_N_mm: float = HAND_K_N_MM, hand_b_N_s_mm: float = HAND_B_N_S_MM) -> None:
        self.mass = (profile.sim_mass_kg + GRIP_KG) * 1e-3
        self.friction = profile.sim_damping_N_s_mm
        self.resolution = profile.resolution_mm
        self.hand_k = hand_k_N_mm
        self.hand_b = hand_b_N_s_mm
        self.x = [float(c) for c in start_mm]
        self.v = [0.0, 0.0, 0.0]
        self.work_mJ = 0.0

    def step(self, force, target, target_v, h: float) -> None:
        """One substep of ``h`` s under ``force`` (N), the hand pulling toward ``target``."""
        x, v = self.x, self.v
        m, c, hk, hb = self.mass, self.friction, self.hand_k, self.hand_b
        work = 0.0
        for i in range(3):
            a = (force[i] + hk * (target[i] - x[i]) + hb * (target_v[i] - v[i])
                 - c * v[i]) / m
            v[i] += a * h
            d = v[i] * h
            work += force[i] * d
            x[i] += d
        self.work_mJ += work

    def advance(self, force, span_s: float, hand_at: Callable[[float], tuple], t0: float) -> None:
        """Integrate over ``span_s`` from time ``t0`` under a constant ``force``, in substeps
        of at most MAX_SUBSTEP_S, the hand's target from ``hand_at(t)``."""
        if span_s <= 0.0:
            return
        n = max(1, math.ceil(span_s / MAX_SUBSTEP_S - 1e-9))
        h = span_s / n
        for i in range(n):
            target, target_v = hand_at(t0 + i * h)
            self.step(force, target, target_v, h)

    def reading(self) -> tuple[float, float, float]:
        """The encoder's reading: each axis quantized to the resolution."""
        r = self.resolution
        return (round(self.x[0] / r) * r, round(self.x[1] / r) * r, round(self.x[2] / r) * r)


def hold(position_mm=(0.0, 0.0, 0.0)) -> HandScript:
    """A hand that holds the grip at one point."""
    p = tuple(float(c) for c in position_mm)
    return lambda t: (p, (0.0, 0.0, 0.0))


def groove(depth_mm: float = 3.0, length_mm: float = 16.0, feed_mm_s: float = 5.0,
           lift_mm: float = 6.0, settle_s: float = 0.5) -> HandScript:
    """A hand that cuts a straight groove along +x through the workspace centre, over and
    over: from (−length/2, 0, lift) down to z = −depth in ``settle_s``, along +x at the feed,
    up, and back above the start. With the default placement the workspace centre is the
    bone's top (``devices.mapping``), so the burr centre dips ``depth_mm`` below it."""
    half = length_mm / 2.0
    t_down = settle_s
    t_cut = length_mm / feed_mm_s
    t_up = settle_s
    t_back = settle_s
    period = t_down + t_cut + t_up + t_back

    def at(t: float):
        t = t % period
        if t < t_down:
            s = t / t_down
            return (-half, 0.0, lift_mm - s * (lift_mm + depth_mm)), \
                (0.0, 0.0, -(lift_mm + depth_mm) / t_down)
        t -= t_down
        if t < t_cut:
            return (-half + feed_mm_s * t, 0.0, -depth_mm), (feed_mm_s, 0.0, 0.0)
        t -= t_cut
        if t < t_up:
            s = t / t_up
            return (half, 0.0, -depth_mm + s * (lift_mm + depth_mm)), \
                (0.0, 0.0, (lift_mm + depth_mm) / t_up)
        s = (t - t_up) / t_back
        return (half - s * length_mm, 0.0, lift_mm), (-length_mm / t_back, 0.0, 0.0)

    return at


def circle(radius_mm: float = 5.0, period_s: float = 2.0) -> HandScript:
    """A hand that moves the grip round a horizontal circle about the workspace centre, once
    every ``period_s``: ``device test`` on the simulated device shows the spring following
    it."""
    w = 2.0 * math.pi / period_s

    def at(t: float):
        c, s = math.cos(w * t), math.sin(w * t)
        return (radius_mm * c, radius_mm * s, 0.0), (-radius_mm * w * s, radius_mm * w * c, 0.0)

    return at


HANDS = {"hold": hold, "groove": groove, "circle": circle}


class SimDevice(HapticDevice):
    """The simulated device in real time: each :meth:`cycle` integrates the mechanism from
    the previous cycle to now under the previous force (what the motors held meanwhile),
    then takes the new force.

    Args:
        profile: whose mass, friction, resolution and limits to simulate (default ``generic``).
        hand: ``hold`` or ``groove`` (``HANDS``), or a HandScript.
        clock: a monotonic clock in ns (tests and benches may drive time themselves).
    """

    def __init__(self, profile: str | DeviceProfile = "generic",
                 hand: str | HandScript = "hold", clock: Callable[[], int] = time.monotonic_ns,
                 **hand_options: float) -> None:
        super().__init__()
        if isinstance(profile, str):
            if profile not in PROFILES:
                raise ValueError(f"unknown profile {profile!r} for the sim device; one of: "
                                 f"{', '.join(PROFILES)}")
            profile = PROFILES[profile]
        if isinstance(hand, str):
            if hand not in HANDS:
                raise ValueError(f"unknown hand script {hand!r}; one of: {', '.join(HANDS)}")
            try:
                hand = HANDS[hand](**hand_options)
            except TypeError:
                accepted = ", ".join(inspect.signature(HANDS[hand]).parameters)
                raise ValueError(f"the {hand!r} hand script has no option "
                                 f"{', '.join(hand_options)}; its options: {accepted or 'none'}"
                                 ) from None
        elif hand_options:
            raise ValueError("hand options apply to a named hand script only")
        self.info = DeviceInfo(backend="sim", model=f"simulated {profile.name}", limits=profile,
                               workspace_radius_mm=profile.sim_workspace_mm,
                               servo_rate_hz=profile.rated_hz, buttons=1)
        self.hand = hand
        self.clock = clock
        start, _ = hand(0.0)
        self.mechanism = SimMechanism(profile, start)
        self.velocity = DeviceVelocity(profile.resolution_mm)
        self.force = np.zeros(3)
        self.t0_ns: int | None = None
        self.t_ns = 0

    def _open(self) -> None:
        self.t0_ns = self.t_ns = self.clock()

    def cycle(self, force_N: np.ndarray) -> DeviceState:
        if self.t0_ns is None:
            raise RuntimeError("open the device first")
        now = self.clock()
        span = (now - self.t_ns) * 1e-9
        t_prev = (self.t_ns - self.t0_ns) * 1e-9
        # Longer gaps than 50 ms (a paused process) are not integrated in one piece.
        self.mechanism.advance(self.force, min(span, 0.05), self.hand, t_prev)
        self.t_ns = now
        self.force, _ = clamp_force(force_N, self.info.limits.max_force_N)
        self.force = self.force.copy()
        x = np.array(self.mechanism.reading())
        t = (now - self.t0_ns) * 1e-9
        v = self.velocity.update(x, t).copy()
        return DeviceState(position_mm=x, velocity_mm_s=v, buttons=1, t_ns=now)
