"""How a session reads its engine's packets: the frame, the placement, the features, the
output, checked once when the settings are made (``SessionConfig``).

A value object the control plane builds, pickles across the hot loop's pipe and the session
applies (``Session.configure``); nothing here runs per packet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ...proto import frames
from ..haptics.config import HapticsConfig
from ..model.vibration import VibrationParams

ZERO3 = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class SessionConfig:
    """How a session reads its engine's packets.

    Attributes:
        frame: engine frame name (``proto.frames.FRAMES``).
        tool_axis: the tool axis in the tool's local frame (from the burr toward the handle),
            engine axes; default the frame's.
        placement_position, placement_orientation: where the server frame (the bone's world)
            lies in the engine's world: engine units and an engine quaternion (x, y, z, w).
        gap_s: a longer silence between accepted packets (client clock) resets the velocity
            estimate.
        max_speed_mm_s: an estimated burr speed above this is a teleport: the estimate is
            reset, not used.
        model: run the bone stage (carving, force). Off, the session answers with zero force:
            the protocol alone (what ``bench latency`` calls the overhead).
        carve: remove bone (off: forces from the bone as it is).
        vibration: vibration parameters, or None for no vibration.
        haptics: the output (raw or coupled) and the device it is for (``HapticsConfig``).
    """

    frame: str = frames.DEFAULT_FRAME
    tool_axis: frames.Vec3 | None = None
    placement_position: frames.Vec3 = ZERO3
    placement_orientation: frames.Quat = (0.0, 0.0, 0.0, 1.0)
    gap_s: float = 0.05
    max_speed_mm_s: float = 2000.0
    model: bool = True
    carve: bool = True
    vibration: VibrationParams | None = field(default_factory=VibrationParams)
    haptics: HapticsConfig = field(default_factory=HapticsConfig)

    def __post_init__(self) -> None:
        frames.frame(self.frame)
        if self.tool_axis is not None:  # stored as unit vectors (frozen: set directly)
            object.__setattr__(self, "tool_axis", unit_vector("tool_axis", self.tool_axis))
        for name, value in (("gap_s", self.gap_s), ("max_speed_mm_s", self.max_speed_mm_s)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not 0.0 < value < math.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if len(self.placement_position) != 3 or not all(
                math.isfinite(x) for x in self.placement_position):
            raise ValueError("placement_position must be 3 finite numbers")
        object.__setattr__(self, "placement_orientation",
                           unit_vector("placement_orientation", self.placement_orientation, 4))


def unit_vector(name: str, v: tuple[float, ...], n: int = 3) -> tuple[float, ...]:
    """``v`` scaled to length 1, as a tuple of ``n`` floats.

    Raises:
        ValueError: ``v`` is not ``n`` finite numbers, or is (about) zero; the message names
            ``name``.
    """
    if len(v) != n or not all(isinstance(x, (int, float)) and math.isfinite(x) for x in v):
        raise ValueError(f"{name} must be {n} finite numbers, got {v!r}")
    # Scaled first: a huge but finite vector must not overflow to an infinite norm.
    scale = max(abs(x) for x in v)
    if scale == 0.0:
        raise ValueError(f"{name} must not be zero")
    w = [x / scale for x in v]
    norm = math.sqrt(sum(x * x for x in w))
    if norm * scale < 1e-6:
        raise ValueError(f"{name} must not be zero")
    return tuple(x / norm for x in w)
