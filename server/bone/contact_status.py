"""A REPLY's contact bits (proto.messages STATUS_*) from one engine step's outputs: the reading
the hot loop's tick makes (the compiled stage and the session's Python tick) and the offline
replay repeats, so a replay compares like with like."""

from __future__ import annotations

import numpy as np

from ...proto.messages import STATUS_CONTACT, STATUS_CUTTING, STATUS_FORBIDDEN, STATUS_SHAFT_CONTACT
from ..hot_kernel import hot_kernel
from ..model.kernels import OUT_CONTACT_AREA, OUT_COUNT
from .shaft import SHAFT_DEPTH, SHAFT_VOLUME


@hot_kernel
def contact_status(out: np.ndarray, shaft_out: np.ndarray, touch_forbidden: float) -> int:
    """The STATUS_* bits of a step: ``out`` and ``shaft_out`` the engine's outputs (float64,
    OUT_* and SHAFT_* layouts), ``touch_forbidden`` its touch[TOUCH_FORBIDDEN]."""
    status = STATUS_FORBIDDEN if touch_forbidden > 0.0 else 0
    if out[OUT_COUNT] > 0.0:
        status |= STATUS_CUTTING
    if out[OUT_CONTACT_AREA] > 0.0:
        status |= STATUS_CONTACT
    if shaft_out[SHAFT_VOLUME] > 0.0 or shaft_out[SHAFT_DEPTH] > 0.0:
        status |= STATUS_SHAFT_CONTACT
    return status
