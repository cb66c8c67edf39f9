"""The real-time scheduler (SCHED_FIFO) for the threads that must run the moment they are
woken: a device's servo loop (``devices.loop``) and, with ``serve --realtime``, each hot
loop's packet thread (``hotloop.child``).

A SCHED_FIFO thread preempts every normal task as soon as it is runnable, instead of waiting
its turn behind them. Allowed for root, with CAP_SYS_NICE, or an ``RLIMIT_RTPRIO`` of at
least the priority asked for; refused, whatever the capabilities, in a cgroup that has no
real-time budget (cgroup v1 with ``CONFIG_RT_GROUP_SCHED``: a container's group gets none by
default). When such a thread keeps its core busy, the kernel still hands normal tasks a share
of it (RT throttling, ``sched_rt_runtime_us``; since Linux 6.12 the fair server), and the
thread waits meanwhile.
"""

from __future__ import annotations

import os

#: A device's servo loop: its 1 kHz force matters more than one packet's round trip.
DEVICE_LOOP_PRIORITY = 10
#: A hot loop's packet thread, below a servo loop on the same machine.
HOT_LOOP_PRIORITY = 5

REFUSED = ("SCHED_FIFO needs root, CAP_SYS_NICE or an RLIMIT_RTPRIO of at least {priority}, "
           "and a cgroup with a real-time budget (cgroup v1 kernels with RT group scheduling "
           "give a container's group none)")


def enter_realtime(priority: int) -> bool:
    """Put the calling thread (not the whole process) under SCHED_FIFO at ``priority``
    (1–99). False, and nothing changes, where that is not permitted."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, OSError):
        return False
    return True


def leave_realtime() -> None:
    """Put the calling thread back under the normal scheduler, keeping its niceness (always
    permitted)."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):  # pragma: no cover - lowering is always allowed
        pass


def is_realtime(tid: int) -> bool:
    """Whether thread ``tid`` (a process's pid names its main thread) runs under SCHED_FIFO;
    False for one that is gone."""
    try:
        return os.sched_getscheduler(tid) == os.SCHED_FIFO
    except (AttributeError, OSError):
        return False
