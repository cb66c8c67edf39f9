"""What the hand feels, stably: velocity estimation, the burr proxy and virtual coupling,
the passivity observer/controller, device limits and device profiles.

See ``coupling`` for the method and ``docs/haptics.md`` for the measured stable regions.
"""

from .config import OUTPUT_MODES, HapticsConfig
from .profiles import PROFILE_NAMES, PROFILES, DeviceProfile, device_profile
from .stage import HapticStage

__all__ = ["OUTPUT_MODES", "PROFILES", "PROFILE_NAMES", "DeviceProfile", "HapticStage",
           "HapticsConfig", "device_profile"]
