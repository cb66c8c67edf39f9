"""A session's haptic stage: the state its numba kernels keep from tick to tick."""

from __future__ import annotations

import numpy as np

from ..bone.shaft import N_SHAFT
from ..model.kernels import N_OUT
from .config import HapticsConfig
from .coupling import coupled_finish, coupled_predict, raw_limits
from .layout import (
    N_RESULT,
    R_B,
    R_ENERGY,
    R_K,
    R_PROXY,
    S_FORCE,
    S_PERIOD,
    S_READY,
    new_state,
)
from .velocity import new_ring, reset, velocity_step


class HapticStage:
    """The haptic output of one session: velocity estimation, the proxy and coupling, the
    passivity observer and the device limits (``config``).

    The session's hot path calls the kernels on these arrays directly (a method call per
    packet costs more than the kernels): ``velocity_step(ring_t, ring_p, ring_state, …)``,
    then ``coupled_predict(state, params, …)`` and ``coupled_finish(state, params, …,
    result)`` around the bone engine, or ``raw_limits(state, params, …)``.
    """

    def __init__(self, config: HapticsConfig, spacing_mm: np.ndarray,
                 max_speed_mm_s: float) -> None:
        self.config = config
        self.coupled = config.coupled
        #: Limits apply (a device profile is set); without one the raw output is untouched.
        self.limited = config.profile is not None
        self.noise_mm = config.noise_mm
        self.window_s = config.velocity_window_s
        self.params = config.params_vector(spacing_mm, max_speed_mm_s)
        self.state = new_state()
        self.result = np.zeros(N_RESULT, dtype=np.float64)
        self.scratch = np.zeros(12, dtype=np.float64)
        self.ring_t, self.ring_p, self.ring_state = new_ring()
        self.centre = np.zeros(3)
        self.feed = np.zeros(3)
        self.device_p = np.zeros(3)
        self.device_v = np.zeros(3)
        self.force = np.zeros(3)

    def restart(self) -> None:
        """A new stream: forget the velocity samples and re-place the proxy on the next
        tick. The force the device renders is kept, so the slew limit starts from it."""
        reset(self.ring_state)
        self.state[S_READY] = 0.0
        self.state[S_PERIOD] = 0.0

    def forget_velocity(self) -> None:
        """A gap or a reset: the next sample starts a new estimate."""
        reset(self.ring_state)

    def device_released(self) -> None:
        """The device was sent zero force (an error reply): limit slew from zero."""
        self.state[S_FORCE:S_FORCE + 3] = 0.0

    def snapshot(self) -> dict[str, object]:
        """The stage's state for status reports (cheap); grid frame, mm, N."""
        r = self.result
        return {"output": self.config.output,
                "profile": None if self.config.profile is None else self.config.profile.name,
                "coupling_stiffness_N_mm": float(r[R_K]),
                "coupling_damping_N_s_mm": float(r[R_B]),
                "passivity_energy_mJ": float(r[R_ENERGY]),
                "proxy_grid_mm": [float(x) for x in r[R_PROXY:R_PROXY + 3]],
                "packet_period_s": float(self.state[S_PERIOD])}


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel of the stage before serving."""
    from .profiles import PROFILES

    stage = HapticStage(HapticsConfig(output="coupled", profile=PROFILES["generic"]),
                        np.full(3, 0.1), 2000.0)
    out = np.zeros(N_OUT)
    shaft = np.zeros(N_SHAFT)
    velocity_step(stage.ring_t, stage.ring_p, stage.ring_state, 0.0, 0.0, 0.0, 0.0,
                  stage.noise_mm, stage.window_s, stage.device_v)
    coupled_predict(stage.state, stage.params, stage.device_p, stage.device_v, 1e-3, True,
                    stage.centre, stage.feed)
    coupled_finish(stage.state, stage.params, out, np.zeros(9), shaft, 1.0, 2.0, stage.result,
                   stage.scratch)
    raw_limits(stage.state, stage.params, stage.force, 1e-3)
