"""Waiting for what happens in the background, bounded: the tests' shared helper."""

from __future__ import annotations

import time
from collections.abc import Callable

#: Bounds on waiting for something that happens in the background; never asserted on.
WAIT_S = 60.0


def wait_until(predicate: Callable[[], object], timeout_s: float = WAIT_S,
               interval_s: float = 0.01) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` passed; its last value, as bool."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval_s)
    return bool(predicate())
