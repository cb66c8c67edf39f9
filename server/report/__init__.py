"""Session reports for an instructor (``burrforce report``, ``GET /v1/recordings/NAME/report``).

- :class:`SessionReport`: duration, time cutting, bone removed per material, forbidden
  contacts, the hand force (peak, mean, time above a threshold) and a plot-sized force series;
  JSON with ``to_dict()``.
- :func:`report_from_recording`: one from a ``.burrrec`` recording (its replies and a replay).
- :func:`report_from_live`: one from a live session's sampled telemetry and its state.
- :func:`render_html`: a self-contained page (inline CSS and SVG, no script).
"""

from .from_live import report_from_live
from .from_recording import report_from_recording
from .html import render_html
from .model import (
    DEFAULT_THRESHOLD_N,
    MAX_THRESHOLD_N,
    ForbiddenContact,
    SessionReport,
    check_threshold,
)
from .series import MAX_SERIES_POINTS, downsample_min_max

__all__ = [
    "DEFAULT_THRESHOLD_N",
    "MAX_SERIES_POINTS",
    "MAX_THRESHOLD_N",
    "ForbiddenContact",
    "SessionReport",
    "check_threshold",
    "downsample_min_max",
    "render_html",
    "report_from_live",
    "report_from_recording",
]
