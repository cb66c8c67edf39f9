"""The pose a burr is evaluated at, validated once at the API edge (units in the names)."""

from __future__ import annotations

import math

import numpy as np

RPM_TO_RAD_S = 2.0 * math.pi / 60.0
# Plausibility bounds at the API edge: far beyond any burr, far below float overflow.
MAX_POSITION_MM = 1e6
MAX_SPEED_MM_S = 1e7
MAX_RPM = 1e7


def check_pose(centre_mm: object, axis: object, feed_mm_s: object,
               rpm: object) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Validated (centre, axis, feed, rpm): float64 (3,) arrays and a float, the axis rescaled
    (``check_axis``). Raises ValueError naming the bad input."""
    centre = check_vec3("centre_mm", centre_mm, MAX_POSITION_MM)
    ax = check_axis("axis", axis)
    feed = check_vec3("feed_mm_s", feed_mm_s, MAX_SPEED_MM_S)
    rpm = float(rpm)  # type: ignore[arg-type]
    if not abs(rpm) <= MAX_RPM:
        raise ValueError(f"rpm must be finite and within ±{MAX_RPM:g}, got {rpm}")
    return centre, ax, feed, rpm


def check_vec3(name: str, value: object, limit: float) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {arr.shape}")
    if not (np.abs(arr) <= limit).all():  # also false for NaN
        raise ValueError(f"{name} must be finite and within ±{limit:g}, got {arr.tolist()}")
    return arr


def check_axis(name: str, value: object) -> np.ndarray:
    """``value`` rescaled so its largest component is ±1: the kernel normalises it, and any
    finite, non-zero magnitude (1e-170 or 1e200) survives that without under- or overflow."""
    arr = check_vec3(name, value, math.inf)
    scale = float(np.abs(arr).max())
    if scale == 0.0:
        raise ValueError(f"{name} must not be zero")
    return arr / scale
