"""The project's own measurements, beside the results pages they write (this folder's ``*.md``,
``*.json``, ``*.png``): not part of the installed burrforce, run from a checkout's root as
``python -m benchmarks.NAME``.

- ``container``: the server image built with podman, against the bare process;
- ``latency``: ``burrforce bench latency`` plus its live-view part (``latency_page``: the
  browser view open on a session, in headless Chromium);
- ``device``: ``burrforce bench device`` with the USB-emulated Falcon (umockdev) in place of
  a real one;
- ``tick_profile``: instructions per bone tick under callgrind; ``gil_probe``: how long other
  threads keep the GIL from the hot loop's.

The benches a user runs on their own machine are ``burrforce bench …`` (``server/bench/``);
the project regenerates this folder's pages with ``--out benchmarks``. The harnesses these
share with the tests (podman, Chromium, the USB emulation) live in ``tests/support``, which
is put on ``sys.path`` here.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

#: The checkout's root (holds this package) and its tests' folder (holds ``support``).
ROOT = Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"

if str(TESTS) not in sys.path:
    sys.path.append(str(TESTS))


def child_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment for a ``python -m benchmarks.…`` child: the checkout's root
    and ``tests/`` on ``PYTHONPATH`` whatever the child's working directory."""
    env = {**os.environ, **(extra or {})}
    paths = [str(ROOT), str(TESTS), *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))]
    env["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(paths))
    return env
