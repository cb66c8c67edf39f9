"""The control plane's background loops (journal, supervisor, telemetry history): each runs on
a daemon thread until its stop event is set."""

from __future__ import annotations

import threading
from collections.abc import Callable

#: How long stopping waits for a loop's thread, s.
JOIN_TIMEOUT_S = 10.0


def start_daemon(target: Callable[[], None], name: str) -> threading.Thread:
    """``target`` on a started daemon thread called ``name``."""
    thread = threading.Thread(target=target, name=name, daemon=True)
    thread.start()
    return thread


def stop_daemon(stop: threading.Event, thread: threading.Thread | None) -> None:
    """Set ``stop`` and wait (bounded) for ``thread``, if there is one."""
    stop.set()
    if thread is not None:
        thread.join(JOIN_TIMEOUT_S)
