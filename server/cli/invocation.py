"""How to type the ``burrforce`` command so that it runs this installation.

What ``serve`` prints for a user to copy must run as typed: after
``python3 -m venv .venv && .venv/bin/pip install -e .`` nothing puts ``.venv/bin`` on PATH, so a
plain ``burrforce`` would be "command not found" (or, worse, another installation's).
"""

from __future__ import annotations

import os
import shlex
import shutil
import sys
import time
from pathlib import Path

SCRIPT = "burrforce"


def burrforce_command() -> str:
    """``burrforce`` when PATH finds this interpreter's own script, else that script's path.

    The script sits beside ``sys.executable`` (a virtualenv's ``bin/``), which is not resolved:
    a venv's python is a symlink to the base interpreter, whose folder holds no such script.
    Without a script there (``python -m burrforce.server.cli``), the interpreter and ``-m``.
    """
    folder = Path(sys.executable).parent
    script = folder / (SCRIPT + ".exe" if os.name == "nt" else SCRIPT)
    if not script.exists():
        return f"{shlex.quote(sys.executable)} -m burrforce.server.cli"
    found = shutil.which(SCRIPT)
    if found and _same_file(Path(found), script):
        return SCRIPT
    return shlex.quote(str(script))


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.samefile(b)
    except OSError:
        return False


def process_age_s() -> float:
    """Seconds since this process started (from ``/proc/self/stat`` on Linux, so the
    interpreter's start-up and imports count; 0 where it cannot tell)."""
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        started_s = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: start time, ticks
        return max(0.0, time.clock_gettime(time.CLOCK_BOOTTIME) - started_s)
    except (OSError, ValueError, IndexError, AttributeError):
        return 0.0
