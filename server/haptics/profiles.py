"""Device profiles: what a haptic device can render, and how the stress harness simulates it.

The cutting force is damping-like (50–100 N·s/m effective for a 4 mm burr), far above what a
desktop device renders stably at 1 kHz. A profile bounds what the coupled output asks of a
device: its peak force, the coupling stiffness it was rated for at its servo rate, and the
largest virtual damping it renders without buzzing. The simulation fields describe the device
for ``burrforce bench stability`` only (the server never reads them).

Units: N, mm, s (stiffness N/mm, damping N·s/mm, slew N/s, mass kg).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace


@dataclass(frozen=True)
class DeviceProfile:
    """Attributes:
    name: the profile's name.
    max_force_N: the largest force sent to the device (peak, not continuous).
    max_stiffness_N_mm: the coupling stiffness the device renders stably at ``rated_hz``.
    max_damping_N_s_mm: the largest virtual damping it renders stably (coupling damping, the
        spring's discretization cost k·T/2, and the passivity controller share it).
    max_slew_N_s: the largest change of force per second sent to the device.
    rated_hz: the update rate the stiffness is rated at; packets slower than this get a
        proportionally softer coupling (Colgate: k·T/2 must stay within the damping budget).
    resolution_mm: position resolution (encoder quantization): the velocity estimator's noise
        bound.
    sim_mass_kg, sim_damping_N_s_mm, sim_workspace_mm: the simulated device of the stress
        harness: end-effector mass, viscous friction, half-width of its cubic workspace.
    """

    name: str
    max_force_N: float
    max_stiffness_N_mm: float
    max_damping_N_s_mm: float
    max_slew_N_s: float
    rated_hz: float = 1000.0
    resolution_mm: float = 0.01
    sim_mass_kg: float = 0.1
    sim_damping_N_s_mm: float = 0.0002
    sim_workspace_mm: float = 80.0

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError("a device profile needs a name")
        for f in fields(self):
            if f.name == "name":
                continue
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value):
                raise ValueError(f"{f.name} must be a finite number, got {value!r}")
            if value < 0.0 or (value == 0.0 and f.name not in ("sim_damping_N_s_mm",)):
                raise ValueError(f"{f.name} must be > 0, got {value!r}")

    def as_dict(self) -> dict[str, float | str]:
        return asdict(self)

    def customized(self, **changes: float) -> DeviceProfile:
        """This profile with some limits changed, named ``custom``."""
        unknown = set(changes) - {f.name for f in fields(self)} - {"name"}
        if unknown:
            raise ValueError(f"unknown device profile field(s): {', '.join(sorted(unknown))}")
        return replace(self, **{"name": "custom", **changes})


# Force, stiffness and damping are the gains CHAI3D 3.3 recommends for stable rendering on
# each device, resolutions the vendors' figures (docs/haptics.md lists the sources). The
# simulated masses and frictions are estimates: no vendor publishes them.
PROFILES: dict[str, DeviceProfile] = {
    p.name: p for p in (
        DeviceProfile("generic", max_force_N=6.0, max_stiffness_N_mm=1.0,
                      max_damping_N_s_mm=0.008, max_slew_N_s=2000.0, resolution_mm=0.02,
                      sim_mass_kg=0.10, sim_damping_N_s_mm=0.0002),
        DeviceProfile("touch", max_force_N=3.3, max_stiffness_N_mm=0.4,
                      max_damping_N_s_mm=0.004, max_slew_N_s=1000.0, resolution_mm=0.055,
                      sim_mass_kg=0.045, sim_damping_N_s_mm=0.0001, sim_workspace_mm=60.0),
        DeviceProfile("falcon", max_force_N=8.0, max_stiffness_N_mm=3.0,
                      max_damping_N_s_mm=0.020, max_slew_N_s=3000.0, resolution_mm=0.0635,
                      sim_mass_kg=0.15, sim_damping_N_s_mm=0.0005, sim_workspace_mm=50.0),
        DeviceProfile("omega3", max_force_N=12.0, max_stiffness_N_mm=5.0,
                      max_damping_N_s_mm=0.030, max_slew_N_s=4000.0, resolution_mm=0.01,
                      sim_mass_kg=0.20, sim_damping_N_s_mm=0.0005, sim_workspace_mm=80.0),
        # Haply Inverse3: force, stiffness, damping and workspace as CHAI3D's Haply port
        # renders it (Haply publishes no datasheet figures for them); slew and resolution
        # are the generic profile's.
        DeviceProfile("inverse3", max_force_N=10.0, max_stiffness_N_mm=1.0,
                      max_damping_N_s_mm=0.006, max_slew_N_s=2000.0, resolution_mm=0.02,
                      sim_mass_kg=0.20, sim_damping_N_s_mm=0.0002, sim_workspace_mm=150.0),
    )
}
#: Named profiles plus ``custom`` (a named one with some limits changed).
PROFILE_NAMES = (*PROFILES, "custom")


def device_profile(name: str, base: str = "generic", **limits: float) -> DeviceProfile:
    """The profile ``name``. ``custom`` is the profile ``base`` with ``limits`` changed
    (``DeviceProfile`` field names)."""
    if name == "custom":
        return device_profile(base).customized(**limits)
    try:
        profile = PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown device profile {name!r}; one of: "
                         f"{', '.join(PROFILE_NAMES)}") from None
    if limits:
        raise ValueError(f"only the custom profile takes limits; {name!r} is fixed")
    return profile
