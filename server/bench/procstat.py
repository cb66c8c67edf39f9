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


def children() -> dict[int, list[int]]:
    """Every process's children, by parent pid (a snapshot of /proc; processes that end while
    it is read are left out)."""
    tree: dict[int, list[int]] = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(os.path.join(entry.path, "stat")) as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        tree.setdefault(ppid, []).append(int(entry.name))
    return tree
