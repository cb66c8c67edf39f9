"""burrforce server: cutting-force model, voxel bone, haptics, hot loop and control plane."""

import time as _time
from importlib.metadata import PackageNotFoundError, version

#: ``time.monotonic()`` when this package was first imported, s: a command's start where its
#: process is older than its interpreter (``cli.invocation.process_age_s``).
IMPORTED_MONOTONIC_S = _time.monotonic()

try:
    __version__ = version("burrforce")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
