"""The server's own folders: its run directory of shared bones (made at start, removed at stop,
and those of killed servers cleaned up), and where the session journal lives in the data
directory.

A run directory (``bone.shared.run_directory``: in ``/dev/shm``, or the temporary directory)
holds the shared bones and the telemetry files of one server; ``OWNER_FILE`` in it names the
process that owns it, so a server started after one killed with SIGKILL can tell a dead
server's directory from a live one's.
"""

from __future__ import annotations

import os
import re
import shutil
import time
from pathlib import Path

from ..bone.shared import OWNER_FILE, run_directory

RUN_DIR_NAME = re.compile(r"burrforce-[a-z0-9_]{8}")
#: An empty run directory without an owner is left alone this long: one being made right now
#: (between ``mkdtemp`` and its owner file) is not a dead server's.
OWNERLESS_GRACE_S = 60.0

__all__ = ["OWNER_FILE", "RunDirectory", "journal_dir", "remove_stale_run_directories"]


def journal_dir(data_dir: Path) -> Path:
    """Where the session journal (``journal``) keeps one folder per session."""
    return Path(data_dir).expanduser() / "journal" / "sessions"


class RunDirectory:
    """This server's run directory: made (with its owner file) when constructed, after the
    stale ones of dead servers beside it were removed; :meth:`remove` at stop."""

    def __init__(self) -> None:
        self.path = run_directory(0)
        remove_stale_run_directories(self.path.parent, keep=self.path)

    def remove(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def remove_stale_run_directories(base: Path, keep: Path) -> list[Path]:
    """Remove the shared-bone directories that servers killed with SIGKILL left in ``base``
    (``/dev/shm``, or the temporary directory): those whose owner process is gone, and
    empty ones without an owner (older servers) once ``OWNERLESS_GRACE_S`` old. Returns what
    was removed."""
    removed = []
    for d in base.glob("burrforce-*"):
        # Only tempfile.mkdtemp's names (run_directory): not a bench's temporary folder.
        if d == keep or not d.is_dir() or not RUN_DIR_NAME.fullmatch(d.name):
            continue
        try:
            pid = int((d / OWNER_FILE).read_text())
        except (OSError, ValueError):
            pid = None
            try:
                if any(d.iterdir()) or time.time() - d.stat().st_mtime < OWNERLESS_GRACE_S:
                    continue  # not ours to judge, or being made
            except OSError:
                continue
        if pid is not None and _alive(pid):
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # somebody else's live process
        return True
    return True
