"""Hypothesis profiles: ``ci`` (every test's own example counts, as CI has always run them)
and ``dev`` (few examples: the fast tier's default, for a quick answer while working).

tests/conftest.py loads one before any test module is imported: ``HYPOTHESIS_PROFILE`` if set,
else ``ci`` for ``pytest --all`` / ``--rest`` and ``dev`` otherwise. A test that asks for its
own count writes ``max_examples=examples(300)``: 300 under ``ci``, at most ``dev``'s count
under ``dev`` (an explicit ``max_examples`` would otherwise override any profile).
"""

from __future__ import annotations

import os

from hypothesis import settings

CI, DEV = "ci", "dev"
#: Examples per test under ``dev`` (and the most any test runs there).
DEV_EXAMPLES = 15
#: Which profile runs when the environment names none: the tier's.
ENV = "HYPOTHESIS_PROFILE"

# numba compiles on first call (seconds with a cold cache): time limits per example would flake.
settings.register_profile(CI, deadline=None)
settings.register_profile(DEV, deadline=None, max_examples=DEV_EXAMPLES)


def load(full_run: bool) -> str:
    """Loads ``$HYPOTHESIS_PROFILE`` if set, else ``ci`` for a full run and ``dev`` for the
    fast tier; returns the profile's name."""
    name = os.environ.get(ENV) or (CI if full_run else DEV)
    settings.load_profile(name)
    return name


def examples(ci: int) -> int:
    """``max_examples`` for a test that runs ``ci`` examples under the ``ci`` profile: as
    many under any profile that runs at least ``ci``'s default count, else capped at the
    loaded profile's count. Call it at import time (in the ``@settings`` decorator)."""
    current = settings.default.max_examples
    if current >= settings.get_profile(CI).max_examples:
        return ci
    return min(ci, current)
