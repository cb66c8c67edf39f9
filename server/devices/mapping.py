"""Where a device's workspace lies in the bone: placement, rotation and scale.

A device reports its end effector in its own frame (``devices.base``: mm, right-handed, the
origin at its workspace centre). The device loop places that frame in the **server frame**
(right-handed mm, z up; the bone's coordinates — a session's own placement, if it has one, is
applied on top exactly as for any engine)::

    x_server = placement_mm + scale · R · x_device
    v_server = scale · R · v_device
    F_device = Rᵀ · F_server            (forces are not scaled)

``scale`` > 1 lets a small workspace reach across a large bone. The hand then feels every
stiffness and damping × scale (1 mm of hand motion is ``scale`` mm of burr motion), so the
renderer keeps k·scale and b·scale within the device's limits (``devices.render``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ...proto.frames import quat_matrix


@dataclass(frozen=True)
class WorkspaceMap:
    """Attributes:
    placement_mm: (3,) where the device's workspace centre lies, server frame, mm.
    rotation: the device frame's orientation in the server frame, a quaternion (x, y, z, w).
    scale: server mm per device mm, > 0.
    """

    placement_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: float = 1.0

    def __post_init__(self) -> None:
        p = tuple(float(c) for c in self.placement_mm)
        if len(p) != 3 or not all(math.isfinite(c) and abs(c) < 1e6 for c in p):
            raise ValueError(f"placement_mm must be 3 finite numbers within ±1e6 mm, got "
                             f"{self.placement_mm!r}")
        q = tuple(float(c) for c in self.rotation)
        if len(q) != 4 or not all(math.isfinite(c) for c in q):
            raise ValueError(f"rotation must be a quaternion (x, y, z, w), got {self.rotation!r}")
        n = math.sqrt(sum(c * c for c in q))
        if not 0.5 <= n <= 1.5:
            raise ValueError(f"rotation must be a unit quaternion (norm {n:.3g})")
        if not (math.isfinite(self.scale) and 0.01 <= self.scale <= 100.0):
            raise ValueError(f"scale must be within [0.01, 100], got {self.scale!r}")
        object.__setattr__(self, "placement_mm", p)
        object.__setattr__(self, "rotation", tuple(c / n for c in q))
        object.__setattr__(self, "_r", quat_matrix(self.rotation))
        object.__setattr__(self, "_p", np.array(p))

    def point(self, x_device_mm: np.ndarray) -> np.ndarray:
        """(3,) device mm → server mm."""
        return self._p + self.scale * (self._r @ x_device_mm)

    def vector(self, v_device: np.ndarray) -> np.ndarray:
        """(3,) a velocity or displacement, device → server (scaled)."""
        return self.scale * (self._r @ v_device)

    def force_to_device(self, f_server_N: np.ndarray) -> np.ndarray:
        """(3,) N, server axes → device axes."""
        return self._r.T @ f_server_N

    def as_dict(self) -> dict:
        return {"placement_mm": list(self.placement_mm), "rotation": list(self.rotation),
                "scale": self.scale}


def bone_top_centre(bone_info: dict | None) -> tuple[float, float, float]:
    """The centre of the top face (largest z) of a bone's bounding box in the server frame,
    from a session's ``bone_info`` (origin_mm, shape, spacing_mm, direction): the default
    placement, so the workspace centre sits on the bone and the hand reaches down into it."""
    if not bone_info or "origin_mm" not in bone_info:
        return (0.0, 0.0, 0.0)
    origin = np.asarray(bone_info["origin_mm"], dtype=float)
    extent = np.asarray(bone_info["shape"], dtype=float) * np.asarray(bone_info["spacing_mm"],
                                                                       dtype=float)
    direction = np.asarray(bone_info.get("direction", np.eye(3)), dtype=float)
    corners = np.array([origin + direction @ (extent * np.array(c)) for c in
                        ((i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1))])
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    return (float((lo[0] + hi[0]) / 2.0), float((lo[1] + hi[1]) / 2.0), float(hi[2]))


def parse_vector(text: str | Sequence[float], n: int, what: str) -> tuple[float, ...]:
    """``"1,2,3"`` or a sequence → a tuple of ``n`` floats (ValueError says what is wrong)."""
    parts = text.split(",") if isinstance(text, str) else list(text)
    try:
        values = tuple(float(p) for p in parts)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be {n} comma-separated numbers, got {text!r}") from None
    if len(values) != n:
        raise ValueError(f"{what} must be {n} numbers, got {len(values)}")
    return values
