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

from .. import IMPORTED_MONOTONIC_S

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


#: A process older than its first import of burrforce by more than this, s, ran something else
#: before it became this interpreter: a shell running ``a && b && burrforce serve`` (the
#: README's first command) execs into its last command, so the process started with the
#: shell, before ``a`` and ``b``.
EXEC_SLACK_S = 2.0


def process_age_s() -> float:
    """Seconds since this command started: since the process started (``/proc/self/stat`` on
    Linux, so the interpreter's start-up and imports count), unless the process was another
    program until long after that (``EXEC_SLACK_S``); then, and where /proc cannot tell,
    since burrforce was first imported."""
    since_import = max(0.0, time.monotonic() - IMPORTED_MONOTONIC_S)
    try:
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        started_s = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22: start time, ticks
        age = time.clock_gettime(time.CLOCK_BOOTTIME) - started_s
    except (OSError, ValueError, IndexError, AttributeError):
        return since_import
    return age if since_import <= age <= since_import + EXEC_SLACK_S else since_import
