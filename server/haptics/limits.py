"""Force limits sent to a device: magnitude clamp and slew-rate limit (numba, in place)."""

from __future__ import annotations

import math

from ..hot_kernel import hot_kernel


@hot_kernel
def limit_force(force, previous, max_force_N, max_step_N):
    """Clamp ``force`` (float64 (3,), N, in place) to ``max_force_N`` in magnitude, then move
    it at most ``max_step_N`` away from ``previous`` (the force sent last tick; the slew limit
    times the tick's duration). Direction is kept by both: a clamp scales the vector, the slew
    limit moves along the straight line between the two forces.

    Returns:
        True if either limit changed the force.
    """
    limited = False
    fx = force[0]
    fy = force[1]
    fz = force[2]
    mag = math.sqrt(fx * fx + fy * fy + fz * fz)
    if mag > max_force_N:
        k = max_force_N / mag
        fx *= k
        fy *= k
        fz *= k
        limited = True
    dx = fx - previous[0]
    dy = fy - previous[1]
    dz = fz - previous[2]
    step = math.sqrt(dx * dx + dy * dy + dz * dz)
    if step > max_step_N:
        k = max_step_N / step
        fx = previous[0] + dx * k
        fy = previous[1] + dy * k
        fz = previous[2] + dz * k
        limited = True
    force[0] = fx
    force[1] = fy
    force[2] = fz
    return limited
