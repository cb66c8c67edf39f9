"""``burrforce replay``: re-run a recorded session offline, exactly or with other materials."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from ..argtypes import float_at_least, float_in

_non_negative_float = float_at_least(0.0, inclusive=True)
_k = float_in(0.0, 100.0, "K")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "replay", help="re-run a recorded session offline and compare it with the recording",
        description="Load a recording (a .burrrec directory written by a session's recorder), "
                    "carve its start snapshot with every recorded tick's burr pose through a "
                    "fresh engine, and compare each tick's force, torque and removal with what "
                    "was recorded. With the recorded parameters the replay is exact; with "
                    "--us-scale or --k it shows what the same hand movements would have felt "
                    "like against other bone. Exit status 1 when a replay with the recorded "
                    "parameters does not reproduce the recording.")
    p.add_argument("recording", type=Path, metavar="RECORDING",
                   help="the recording's .burrrec directory")
    p.add_argument("--json", action="store_true", help="print a JSON object")
    p.add_argument("--us-scale", type=_non_negative_float, default=1.0, metavar="X",
                   help="multiply every material's specific cutting energy Us by X. Default 1")
    p.add_argument("--k", type=_k, default=None, metavar="K",
                   help="set every material's normal/tangential force ratio K")
    p.add_argument("--csv", type=Path, metavar="PATH",
                   help="write the per-tick forces to this CSV file")
    p.add_argument("--bone-out", type=Path, metavar="PATH.bone.npz",
                   help="save the bone as the replay left it (.bone.npz)")
    p.set_defaults(func=run)


def _check_writable(path: Path | None, what: str) -> None:
    """Fail before the replay, not after it."""
    if path is None:
        return
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise OSError(f"cannot write the {what} to {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK):
        raise OSError(f"cannot write the {what} to {path}: {parent} is not writable")


def run(args: argparse.Namespace) -> int:
    from ..bone.loaders import save_bone
    from ..record import read_recording, replay
    from .compile_jobs import RECORDINGS
    from .first_start import compile_before_use

    _check_writable(args.csv, "CSV")
    _check_writable(args.bone_out, "bone")
    recording = read_recording(args.recording)
    compile_before_use((RECORDINGS,), "a replay", sys.stderr)
    for problem in recording.problems:
        print(f"warning: {problem}", file=sys.stderr)
    progress = _Progress(len(recording.rows))
    try:
        report = replay(recording, us_scale=args.us_scale, k=args.k, progress=progress)
    finally:
        progress.close()
    if args.csv is not None:
        report.write_csv(args.csv)
        print(f"per-tick forces written to {args.csv}", file=sys.stderr)
    if args.bone_out is not None:
        path = save_bone(report.bone, args.bone_out)
        print(f"bone written to {path}", file=sys.stderr)
    if args.json:
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(report.format_text())
    if not report.overrides and not report.reproduced:
        print("burrforce replay: the replay does not reproduce the recording (another "
              "machine or burrforce version, or a bone changed behind the session's back)",
              file=sys.stderr)
        return 1
    return 0


class _Progress:
    """A tqdm bar on stderr, silent when stderr is not a terminal."""

    def __init__(self, total: int) -> None:
        from tqdm import tqdm

        self._bar = tqdm(total=total, desc="replay", unit="tick", file=sys.stderr,
                         disable=None, leave=False)

    def __call__(self, done: int, total: int) -> None:
        if done > self._bar.n:
            self._bar.update(done - self._bar.n)

    def close(self) -> None:
        self._bar.close()
