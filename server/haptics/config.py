"""A session's haptic output settings: which output, for which device."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .layout import (
    N_PARAMS,
    P_DEPTH_FLOOR,
    P_MAX_DAMPING,
    P_MAX_FORCE,
    P_MAX_SLEW,
    P_MAX_SPEED,
    P_MAX_STIFFNESS,
    P_PERIOD_GAIN,
    P_PROXY_MASS,
    P_PUSH_OUT,
    P_RATED_PERIOD,
    P_SKIN,
    P_TRIAL_RELAX,
)
from .profiles import PROFILES, DeviceProfile

#: ``raw``: the model's force as is (research; within the device's force and slew limits if
#: a device profile is set). ``coupled``: a proxy and a virtual coupling (devices).
OUTPUT_MODES = ("raw", "coupled")


@dataclass(frozen=True)
class HapticsConfig:
    """Attributes:
    output: ``raw`` or ``coupled`` (``OUTPUT_MODES``).
    profile: the device the force is for. None (only with ``raw``): no device, no limits —
        the model's force unchanged. ``coupled`` without a profile uses ``generic``.
    proxy_mass_kg: the proxy's mass: inertia the hand feels through the coupling (small).
    contact_skin_mm: how deep a rigid contact may stay unresolved (a resting contact keeps a
        measurable overlap, so its normal stays known from tick to tick).
    push_out: share of a deeper penetration resolved per tick, (0, 1].
    velocity_noise_mm: the velocity estimator's position noise bound; None: the profile's
        resolution (an end-fit line through two quantized samples is off by up to a whole
        quantum: half a quantum rejects every window longer than two samples after each
        step), or 0.001 mm without a profile (an engine's float pose).
    velocity_window_s: the estimator's longest window.
    trial_relax: how far the feed the bone engine evaluates moves toward each tick's guess of
        the proxy's velocity, (0, 1] (``coupling.coupled_predict``).
    """

    output: str = "raw"
    profile: DeviceProfile | None = None
    proxy_mass_kg: float = 0.002
    contact_skin_mm: float = 0.02
    push_out: float = 0.3
    velocity_noise_mm: float | None = None
    velocity_window_s: float = 0.02
    trial_relax: float = 0.5

    def __post_init__(self) -> None:
        if self.output not in OUTPUT_MODES:
            raise ValueError(f"output must be one of {', '.join(OUTPUT_MODES)}, "
                             f"got {self.output!r}")
        if self.output == "coupled" and self.profile is None:
            object.__setattr__(self, "profile", PROFILES["generic"])
        if self.profile is not None and not isinstance(self.profile, DeviceProfile):
            raise ValueError(f"profile must be a DeviceProfile, got {self.profile!r}")
        for name, lo, lo_open, hi in (("proxy_mass_kg", 0.0, True, 10.0),
                                      ("contact_skin_mm", 0.0, False, 10.0),
                                      ("push_out", 0.0, True, 1.0),
                                      ("trial_relax", 0.0, True, 1.0),
                                      ("velocity_window_s", 0.0, True, 10.0)):
            _check(name, getattr(self, name), lo, lo_open, hi)
        if self.velocity_noise_mm is not None:
            _check("velocity_noise_mm", self.velocity_noise_mm, 0.0, False, 100.0)

    @classmethod
    def for_device(cls, profile: DeviceProfile | None, output: str | None = None,
                   **settings: float) -> HapticsConfig:
        """The settings for ``profile``; without an explicit ``output``, a device gets the
        coupled output and no device the raw one."""
        if output is None:
            output = "raw" if profile is None else "coupled"
        return cls(output=output, profile=profile, **settings)

    @property
    def coupled(self) -> bool:
        return self.output == "coupled"

    @property
    def noise_mm(self) -> float:
        if self.velocity_noise_mm is not None:
            return self.velocity_noise_mm
        return self.profile.resolution_mm if self.profile is not None else 0.001

    def params_vector(self, spacing_mm: np.ndarray, max_speed_mm_s: float) -> np.ndarray:
        """The numba kernels' parameters (``layout.P_*``), float64 (N_PARAMS,); all zero
        limits without a profile (the stage is then skipped)."""
        p = np.zeros(N_PARAMS, dtype=np.float64)
        d = self.profile
        if d is not None:
            p[P_MAX_FORCE] = d.max_force_N
            p[P_MAX_STIFFNESS] = d.max_stiffness_N_mm
            p[P_MAX_DAMPING] = d.max_damping_N_s_mm
            p[P_MAX_SLEW] = d.max_slew_N_s
            p[P_RATED_PERIOD] = 1.0 / d.rated_hz
        p[P_PROXY_MASS] = self.proxy_mass_kg * 1e-3
        p[P_SKIN] = self.contact_skin_mm
        # Depths below half a voxel are not resolved by the partial-volume contact area.
        p[P_DEPTH_FLOOR] = 0.5 * float(np.min(spacing_mm))
        p[P_MAX_SPEED] = max_speed_mm_s
        p[P_PUSH_OUT] = self.push_out
        p[P_PERIOD_GAIN] = 0.1
        p[P_TRIAL_RELAX] = self.trial_relax
        return p


def _check(name: str, value: object, lo: float, lo_open: bool, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or value > hi or value < lo \
            or (lo_open and value == lo):
        bound = ">" if lo_open else "≥"
        raise ValueError(f"{name} must be {bound} {lo} and ≤ {hi}, got {value!r}")
