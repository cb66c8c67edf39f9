"""Registers the SDK harness's fixtures (``harness.py``) for the tests in this folder."""

from harness import live_server, python_groove, rest  # noqa: F401  (fixtures)
