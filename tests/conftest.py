"""Shared fixtures: the thesis's cases and their converged references (computed once)."""

from __future__ import annotations

import pytest
from hypothesis import settings

from burrforce.server.model import CuttingParams, thesis_cases
from burrforce.server.model.reference import reference_case

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
