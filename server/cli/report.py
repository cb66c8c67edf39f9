"""``burrforce report``: a session report (text, JSON or HTML) from a recording."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..argtypes import float_at_least
from .replay import _check_writable, _Progress

_positive = float_at_least(0.0, inclusive=False)


def _threshold(text: str) -> float:
    from ..report import MAX_THRESHOLD_N

    value = _positive(text)
    if value > MAX_THRESHOLD_N:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_THRESHOLD_N:g} N, got {text}")
    return value


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..report import DEFAULT_THRESHOLD_N

    p = sub.add_parser(
        "report", help="a session report of a recording: time, removal, forbidden contacts, "
                       "hand force",
        description="Report on a recorded session for an instructor: duration, time cutting, "
                    "bone removed per material, forbidden contacts (time, structure, "
                    "position), the hand force (peak, mean in contact, time above a "
                    "threshold) and a plot of it. The recording is replayed for the volumes "
                    "and contacts, which takes about as long as the session took to compute.")
    p.add_argument("recording", type=Path, metavar="RECORDING",
                   help="the recording's .burrrec directory")
    p.add_argument("--threshold-n", type=_threshold, default=DEFAULT_THRESHOLD_N, metavar="X",
                   help=f"the hand-force threshold, N. Default {DEFAULT_THRESHOLD_N:g}")
    p.add_argument("--html", type=Path, metavar="PATH",
                   help="also write the report as a self-contained HTML page")
    p.add_argument("--json", action="store_true", help="print a JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..record import read_recording
    from ..report import render_html, report_from_recording
    from .compile_jobs import RECORDINGS
    from .first_start import compile_before_use

    _check_writable(args.html, "HTML report")
    recording = read_recording(args.recording)
    compile_before_use((RECORDINGS,), "a replay", sys.stderr)
    progress = _Progress(len(recording.rows))
    try:
        report = report_from_recording(recording, args.threshold_n, progress=progress)
    finally:
        progress.close()
    if args.html is not None:
        args.html.write_text(render_html(report), encoding="utf-8")
        print(f"HTML report written to {args.html}", file=sys.stderr)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2, allow_nan=False))
    else:
        print(report.format_text())
    return 0
