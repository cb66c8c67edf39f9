"""What the hand feels, stably: velocity estimation, the burr proxy and virtual coupling,
the passivity observer/controller, device limits and device profiles.

See ``coupling`` for the method and ``docs/haptics.md`` for the measured stable regions.
"""

from importlib import import_module

from .config import OUTPUT_MODES, HapticsConfig
from .profiles import PROFILE_NAMES, PROFILES, DeviceProfile, device_profile

__all__ = ["OUTPUT_MODES", "PROFILES", "PROFILE_NAMES", "DeviceProfile", "HapticStage",
           "HapticsConfig", "device_profile"]


def __getattr__(name: str):
    # The stage (numba kernels, the bone's shaft) on first use (PEP 562): the profiles and the
    # configuration alone are what the command line and the settings need.
    if name != "HapticStage":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = import_module(".stage", __name__).HapticStage
    globals()[name] = value
    return value
