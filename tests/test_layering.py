"""The house's layering, as pyproject.toml's import-linter contracts state it: each room of
``server/`` imports only from rooms below it, the protocol and the clients import nothing of
the server, and no room's modules import each other in a circle (imports inside functions
and under ``TYPE_CHECKING`` count too)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_every_layering_contract_is_kept():
    out = subprocess.run([sys.executable, "-c",
                          "import sys; from importlinter.cli import lint_imports_command; "
                          "sys.exit(lint_imports_command())"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    kept = re.search(r"Contracts: (\d+) kept, 0 broken", out.stdout)
    assert kept and int(kept.group(1)) >= 6, out.stdout  # none dropped from pyproject.toml
