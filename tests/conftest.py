"""Shared fixtures: the thesis's cases and their converged references (computed once); CI's
rule that a test skipped for want of a system part fails."""

from __future__ import annotations

import os

import pytest
from hypothesis import settings

from burrforce.server import compile_cache

# Before numba is imported: the tests and the `burrforce` processes they start then share the
# command's cache, instead of a fresh machine compiling every kernel twice.
compile_cache.configure()

from burrforce.server.model import CuttingParams, thesis_cases  # noqa: E402
from burrforce.server.model.reference import reference_case  # noqa: E402

# numba compiles on first call (seconds with a cold cache): time limits per example would flake.
settings.register_profile("burrforce", deadline=None)
settings.load_profile("burrforce")


@pytest.fixture(scope="session")
def thesis_params() -> CuttingParams:
    return CuttingParams()


@pytest.fixture(scope="session")
def nine_cases():
    return list(thesis_cases())


@pytest.fixture(scope="session")
def nine_references(nine_cases, thesis_params):
    return [reference_case(c, thesis_params) for c in nine_cases]


#: Set by .ci/run, which installs everything the tests need (umockdev, PortAudio, JACK, ...):
#: there a skip means a missing install step, so it fails — unless its reason says the skip
#: is about this machine's state, not its software ("(allowed in CI)").
STRICT_SKIPS = os.environ.get("BURRFORCE_STRICT_SKIPS") == "1"
ALLOWED_SKIP = "(allowed in CI)"


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if STRICT_SKIPS and report.skipped and not hasattr(report, "wasxfail"):
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else \
            str(report.longrepr)
        if ALLOWED_SKIP not in reason:
            report.outcome = "failed"
            report.longrepr = (f"skipped in CI, where .ci/run installs everything the tests "
                               f"need: {reason}")
