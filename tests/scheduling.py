"""Whether this machine lets a test's processes use the real-time scheduler."""

from __future__ import annotations

import os

from burrforce.server.realtime import HOT_LOOP_PRIORITY, REFUSED, enter_realtime

FIFO_REASON = "SCHED_FIFO is not permitted here: " + REFUSED.format(priority=HOT_LOOP_PRIORITY)


def fifo_permitted(priority: int = HOT_LOOP_PRIORITY) -> bool:
    """Whether this process may use SCHED_FIFO at ``priority``: tried in a child, so nothing
    here changes."""
    pid = os.fork()
    if pid == 0:
        os._exit(0 if enter_realtime(priority) else 1)
    return os.waitpid(pid, 0)[1] == 0
