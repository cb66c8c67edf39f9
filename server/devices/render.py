"""The device side of SPEC 7.5: re-render the newest coupling model at the servo rate.

A REPLY carries the coupling model — the proxy's position and velocity, the coupling's
stiffness k and damping b — valid at the moment its POSE was sampled. Between replies the
device host renders, every servo tick, from its own newest reading::

    p̂ = proxy_position + proxy_velocity · age      (age: since the POSE was sampled, capped)
    F = k·(p̂ − x) + b·(proxy_velocity − v)

so the spring follows the hand between packets instead of holding a force computed for where
the hand was. Extrapolating the proxy by its own velocity removes the first-order effect of
the round trip (a proxy that moved on during the delay is not pulled back to where it was).

Delay still makes a sampled spring active (the hand is pulled toward a proxy that answered an
older position), so a passivity observer and controller run here too, at the servo rate, on
the device's own displacements (``haptics.passivity``'s controller; the server's observer
runs per packet and cannot see the hand between packets). The observer's reserve is capped at
the energy a coupling spring holds at the device's maximum force, F_max²/(2·k_max), as on the
server.

A reply without a coupling model (``coupling_stiffness == 0``: raw output) is rendered as its
``force``, held.

Watchdog: no model, or the newest model older than ``stale_s`` (default 30 ms), renders zero —
immediately, not slew-limited — and counts a trip. The device loop sends that zero on its next
cycle, so with a 1 kHz servo loop the force is zero within stale_s + 1 ms of the last reply.

All of it is one numba call per servo tick on float64 arrays (``render``); ``CouplingRenderer``
owns the arrays. Units: mm, s, N (k N/mm, b N·s/mm), energy N·mm (= mJ).
"""

from __future__ import annotations

import math

import numpy as np

from ..haptics.limits import limit_force
from ..haptics.passivity import control
from ..haptics.profiles import DeviceProfile
from ..hot_kernel import hot_kernel

# -- the coupling model (what the newest good reply said) -------------------------------------
M_VALID = 0  # 1 once a model is held
M_T_SAMPLE = 1  # s, device clock: when the answered POSE was sampled
M_T_ARRIVAL = 2  # s, device clock: when the reply arrived
M_K = 3  # N/mm (0: no coupling model: render M_FORCE)
M_B = 4  # N·s/mm
M_PROXY = 5  # 3 × mm
M_PROXY_V = 8  # 3 × mm/s
M_FORCE = 11  # 3 × N: the reply's force (raw output)
N_MODEL = 14

# -- parameters --------------------------------------------------------------------------------
P_MAX_FORCE = 0  # N
P_MAX_SLEW = 1  # N/s
P_MAX_DAMPING = 2  # N·s/mm: bound of b, and (separately) of the controller's damping
P_MAX_STIFFNESS = 3  # N/mm: bound of k as the device feels it
P_STALE = 4  # s
P_MAX_AGE = 5  # s: extrapolation is capped at this age
P_RESERVE = 6  # mJ: the observer's cap
P_SCALE = 7  # device mm → session mm (devices.mapping): k and b are felt × this
P_PASSIVITY = 8  # 1: run the observer/controller
N_PARAMS = 9

# -- state --------------------------------------------------------------------------------------
S_FORCE = 0  # 3 × N, the force commanded last tick
S_X_PREV = 3  # 3 × mm, the position last tick
S_HAVE_PREV = 6
S_T_PREV = 7  # s
S_ENERGY = 8  # mJ, the observer
S_STALE = 9  # 1 while the watchdog holds the force at zero
S_ALPHA = 10  # N·s/mm, the controller's damping last tick
N_STATE = 11

# -- counters (int64) --------------------------------------------------------------------------
C_TICKS = 0
C_SATURATED = 1  # ticks whose force the force or slew limit changed
C_TRIPS = 2  # watchdog trips (a model went stale, or none ever came)
C_PASSIVITY = 3  # ticks the controller added damping
C_ZERO = 4  # ticks rendered as zero by the watchdog
N_COUNTERS = 5

#: Defaults: zero within 30 ms of the last reply (SPEC 7.6 asks ≤ 50 ms), extrapolate ≤ 50 ms.
STALE_S = 0.03
MAX_AGE_S = 0.05


@hot_kernel
def render(params, model, state, counters, x_mm, v_mm_s, t_s, out_N):
    """One servo tick: the force to command now, into ``out_N`` (float64 (3,), N, the
    session's axes, before mapping to the device).

    Args:
        params (N_PARAMS,), model (N_MODEL,), state (N_STATE,): float64; counters
            (N_COUNTERS,) int64 — all updated in place except params and model.
        x_mm, v_mm_s: (3,) the device's position and velocity in the session frame.
        t_s: now, on the clock of ``model``'s times.

    Returns:
        True if the force is live (a fresh model), False if the watchdog zeroed it.
    """
    counters[C_TICKS] += 1
    dt = t_s - state[S_T_PREV] if state[S_HAVE_PREV] > 0.0 else 0.0
    if state[S_HAVE_PREV] > 0.0 and params[P_PASSIVITY] > 0.0:
        work = 0.0  # the last force over this tick's displacement: what the device got
        for i in range(3):
            work += state[S_FORCE + i] * (x_mm[i] - state[S_X_PREV + i])
        energy = min(state[S_ENERGY] - work, params[P_RESERVE])
        # A non-finite reading must not poison the observer for good.
        state[S_ENERGY] = energy if math.isfinite(energy) else 0.0
    for i in range(3):
        state[S_X_PREV + i] = x_mm[i]
    state[S_HAVE_PREV] = 1.0
    state[S_T_PREV] = t_s
    fresh = model[M_VALID] > 0.0 and t_s - model[M_T_ARRIVAL] <= params[P_STALE]
    if not fresh:
        if state[S_STALE] == 0.0:
            counters[C_TRIPS] += 1
            state[S_STALE] = 1.0
        counters[C_ZERO] += 1
        for i in range(3):
            out_N[i] = 0.0
            state[S_FORCE + i] = 0.0
        state[S_ALPHA] = 0.0
        return False
    state[S_STALE] = 0.0
    scale = params[P_SCALE]
    k = model[M_K]
    if k > 0.0:
        # The device feels k·scale and b·scale (the hand moves 1 mm, the proxy's spring sees
        # scale mm): keep both within what the device renders.
        k = min(k, params[P_MAX_STIFFNESS] / scale)
        b = min(model[M_B], params[P_MAX_DAMPING] / scale)
        # A spring whose other end answers a round trip late leaks about k·delay·v² (as a
        # sampled one leaks k·T/2·v²): keep k·delay within the damping the device renders.
        delay = model[M_T_ARRIVAL] - model[M_T_SAMPLE]
        if delay > 0.0:
            k = min(k, params[P_MAX_DAMPING] / (scale * delay))
        age = min(max(t_s - model[M_T_SAMPLE], 0.0), params[P_MAX_AGE])
        for i in range(3):
            p = model[M_PROXY + i] + model[M_PROXY_V + i] * age
            out_N[i] = k * (p - x_mm[i]) + b * (model[M_PROXY_V + i] - v_mm_s[i])
    else:
        for i in range(3):
            out_N[i] = model[M_FORCE + i]
    alpha = 0.0
    if params[P_PASSIVITY] > 0.0 and dt > 0.0:
        # The controller sees the device's own velocity (device mm/s → session: × scale).
        alpha = control(state[S_ENERGY], out_N, v_mm_s, dt, params[P_MAX_DAMPING] / scale)
        if alpha > 0.0:
            counters[C_PASSIVITY] += 1
    state[S_ALPHA] = alpha
    step = params[P_MAX_SLEW] * (dt if dt > 0.0 else 1e-3)
    if limit_force(out_N, state[S_FORCE:S_FORCE + 3], params[P_MAX_FORCE], step):
        counters[C_SATURATED] += 1
    for i in range(3):
        if not math.isfinite(out_N[i]):
            out_N[0] = 0.0
            out_N[1] = 0.0
            out_N[2] = 0.0
            break
    for i in range(3):
        state[S_FORCE + i] = out_N[i]
    return True


class CouplingRenderer:
    """The coupling model and renderer of one device loop.

    Args:
        limits: the device's profile (max force, slew, stiffness and damping).
        scale: session mm per device mm (``devices.mapping``).
        stale_s: the watchdog's age limit, ≤ 0.05 s (SPEC 7.6).
        max_age_s: extrapolation cap.
        passivity: run the servo-rate passivity observer/controller.
    """

    def __init__(self, limits: DeviceProfile, scale: float = 1.0, stale_s: float = STALE_S,
                 max_age_s: float = MAX_AGE_S, passivity: bool = True) -> None:
        if not 0.0 < stale_s <= 0.05:
            raise ValueError(f"stale_s must be in (0, 0.05] s (zero force within 50 ms of a "
                             f"stale model), got {stale_s!r}")
        if not (math.isfinite(scale) and scale > 0.0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        self.params = np.zeros(N_PARAMS)
        self.params[P_MAX_FORCE] = limits.max_force_N
        self.params[P_MAX_SLEW] = limits.max_slew_N_s
        self.params[P_MAX_DAMPING] = limits.max_damping_N_s_mm
        self.params[P_MAX_STIFFNESS] = limits.max_stiffness_N_mm
        self.params[P_STALE] = stale_s
        self.params[P_MAX_AGE] = max_age_s
        # Energies are observed on session-frame displacements (× scale).
        self.params[P_RESERVE] = scale * limits.max_force_N ** 2 / (
            2.0 * limits.max_stiffness_N_mm)
        self.params[P_SCALE] = scale
        self.params[P_PASSIVITY] = 1.0 if passivity else 0.0
        self.model = np.zeros(N_MODEL)
        self.state = np.zeros(N_STATE)
        self.counters = np.zeros(N_COUNTERS, dtype=np.int64)
        self.force_N = np.zeros(3)

    def accept(self, t_sample_s: float, t_arrival_s: float, proxy_mm, proxy_v_mm_s,
               k_N_mm: float, b_N_s_mm: float, force_N) -> None:
        """Hold a good reply's coupling model (error 0, verified, newer than the last)."""
        m = self.model
        m[M_T_SAMPLE] = t_sample_s
        m[M_T_ARRIVAL] = t_arrival_s
        m[M_K] = k_N_mm
        m[M_B] = b_N_s_mm
        m[M_PROXY:M_PROXY + 3] = proxy_mm
        m[M_PROXY_V:M_PROXY_V + 3] = proxy_v_mm_s
        m[M_FORCE:M_FORCE + 3] = force_N
        m[M_VALID] = 1.0 if np.all(np.isfinite(m)) else 0.0

    def drop(self) -> None:
        """Forget the model (an error reply, a new stream): zero force until the next one."""
        self.model[M_VALID] = 0.0

    def render(self, x_mm: np.ndarray, v_mm_s: np.ndarray, t_s: float) -> np.ndarray:
        """The force for this tick, (3,) N (the same array every call: copy to keep it)."""
        render(self.params, self.model, self.state, self.counters, x_mm, v_mm_s, t_s,
               self.force_N)
        return self.force_N

    @property
    def live(self) -> bool:
        return self.state[S_STALE] == 0.0 and self.model[M_VALID] > 0.0

    def warm_up(self) -> None:
        """Compile the kernel before the servo loop starts (then forget the warm-up)."""
        x = np.zeros(3)
        self.accept(0.0, 0.0, x, x, 0.1, 0.001, x)
        self.render(x, x, 0.001)
        self.render(x, x, 0.002)
        self.model[:] = 0.0
        self.state[:] = 0.0
        self.counters[:] = 0
