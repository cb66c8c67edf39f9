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
