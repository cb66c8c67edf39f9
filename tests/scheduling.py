"""Whether this machine lets a test's processes use the real-time scheduler."""

from __future__ import annotations

import os

from burrforce.server.hotloop.process import HOT_LOOP_RT_PRIORITY, enter_realtime

FIFO_REASON = ("SCHED_FIFO is not permitted here (needs root, CAP_SYS_NICE or an "
               f"RLIMIT_RTPRIO of {HOT_LOOP_RT_PRIORITY})")


def fifo_permitted() -> bool:
    """Whether this process may use SCHED_FIFO: tried in a child, so nothing here changes."""
    pid = os.fork()
    if pid == 0:
        os._exit(0 if enter_realtime() else 1)
    return os.waitpid(pid, 0)[1] == 0
