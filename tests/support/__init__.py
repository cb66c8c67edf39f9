"""What the tests and the project's own measurements (``benchmarks/``) drive besides burrforce
itself, kept out of the installed package: USB devices emulated with umockdev (``emulation``),
podman for the server image (``podman``), headless Chromium (``chromium``).

Imported as ``support`` with ``tests/`` on ``sys.path``: pytest puts it there (the tests'
``conftest.py`` lives in it), ``benchmarks/__init__.py`` adds it, and the emulator's own
process gets it through ``PYTHONPATH`` (``emulation.launcher``).
"""
