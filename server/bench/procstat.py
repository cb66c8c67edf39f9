"""CPU time of processes, from Linux's /proc: what the benches charge to a server, a load
generator or a browser (CPU time, unlike wall time, is not inflated by other work on a busy
machine)."""

from __future__ import annotations

import os

CLK_TCK = os.sysconf("SC_CLK_TCK")


def cpu_s(pid: int) -> float | None:
    """utime + stime of process ``pid`` (all its threads), s; None if it is gone or /proc
    cannot tell."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK  # fields 14 and 15 of proc(5)
    except (OSError, ValueError, IndexError):
        return None
