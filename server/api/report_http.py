"""How the report routes (a recording's, a live session's) answer: the query parameters they
share and the response, JSON or a script-free HTML page."""

from __future__ import annotations

from fastapi import Query
from fastapi.responses import HTMLResponse, JSONResponse, Response

from ..report import DEFAULT_THRESHOLD_N, MAX_THRESHOLD_N, SessionReport, render_html

#: The report page has no script and loads nothing: it may only style itself and show
#: data: images.
REPORT_CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
ReportFormat = Query("json", description="json, or html: a page for an instructor")
ReportThreshold = Query(DEFAULT_THRESHOLD_N, gt=0.0, le=MAX_THRESHOLD_N, allow_inf_nan=False,
                        description="the hand-force threshold, N: the report counts the time "
                                    "above it")
REPORT_RESPONSES = {200: {"description": "the session report: JSON (``SessionReport.to_dict``) "
                                         "or a self-contained HTML page",
                          "content": {"text/html": {"schema": {"type": "string"}}}}}


def report_response(report: SessionReport, format: str) -> Response:
    """``report`` as JSON, or as the HTML page under ``REPORT_CSP``."""
    if format == "html":
        return HTMLResponse(render_html(report),
                            headers={"Content-Security-Policy": REPORT_CSP})
    return JSONResponse(report.to_dict())
