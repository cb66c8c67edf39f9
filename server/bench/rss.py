"""Resident memory of a process, from Linux's /proc: what a bench or test charges to a
server while it loads a bone.

The peak is the kernel's own (``VmHWM``), reset before each measurement where this process
may (``/proc/PID/clear_refs``: its owner or root), so a short spike between two samples is
not missed; where it may not, the highest of samples taken every few milliseconds.
"""

from __future__ import annotations

import threading
import time


def _status_kib(pid: int, field: str) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def rss_bytes(pid: int) -> int | None:
    """Resident memory of ``pid`` now (anonymous, file and shared pages), bytes."""
    kib = _status_kib(pid, "VmRSS")
    return None if kib is None else kib * 1024


def peak_rss_bytes(pid: int) -> int | None:
    """The most resident memory ``pid`` had since it started or its peak was reset."""
    kib = _status_kib(pid, "VmHWM")
    return None if kib is None else kib * 1024


def reset_peak(pid: int) -> bool:
    """Start ``pid``'s peak afresh from its present resident memory (Linux ≥ 4.0)."""
    try:
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


class PeakRss:
    """The peak resident memory of ``pid`` from entering the ``with`` block to leaving it.

    Attributes:
        before: resident memory on entry, bytes.
        peak: the peak within the block, bytes (the kernel's when it could be reset, else
            the highest sample; both when both are known).
        exact: the kernel's peak was reset and read.
    """

    def __init__(self, pid: int, interval_s: float = 0.005) -> None:
        self.pid = pid
        self.interval_s = interval_s
        self.before = 0
        self.peak = 0
        self.exact = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> PeakRss:
        self.before = rss_bytes(self.pid) or 0
        self.exact = reset_peak(self.pid)
        self.peak = self.before
        self._thread = threading.Thread(target=self._sample, name="peak-rss", daemon=True)
        self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_bytes(self.pid) or 0)
            time.sleep(self.interval_s)

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self.exact:
            self.peak = max(self.peak, peak_rss_bytes(self.pid) or 0)
