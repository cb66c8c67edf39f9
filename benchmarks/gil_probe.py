"""How long other threads keep the GIL from a thread that wants it, and who they were.

A probe thread sleeps ``period_s`` in a loop inside a nogil numba function (the GIL released,
as the hot loop's packet thread waits in ``recvfrom``), which reads the clock the moment the
sleep ends; the Python code after it reads the clock again once the thread holds the GIL. The
difference is the wait for the GIL alone: unlike the lateness of the whole wake-up it does not
count the timer's slack or the scheduler's delays, which on a shared machine are as large.
A wait longer than ``report_s`` also records where the watched thread stands at that moment
(``sys._current_frames``): the code that held the GIL until just now.
"""

from __future__ import annotations

import ctypes
import sys
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numba import njit

_libc = ctypes.CDLL(None, use_errno=True)
_clock_gettime = _libc.clock_gettime
_clock_gettime.argtypes = (ctypes.c_int, ctypes.c_void_p)
_clock_gettime.restype = ctypes.c_int
_clock_nanosleep = _libc.clock_nanosleep
_clock_nanosleep.argtypes = (ctypes.c_int, ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p)
_clock_nanosleep.restype = ctypes.c_int
#: time.perf_counter_ns's clock on Linux.
_CLOCK_MONOTONIC = 1


@njit(nogil=True)
def _nap(timespec, now):
    """Sleep ``timespec`` (int64 [s, ns]) without the GIL; the monotonic time it ended, ns."""
    _clock_nanosleep(_CLOCK_MONOTONIC, 0, timespec.ctypes.data, 0)
    _clock_gettime(_CLOCK_MONOTONIC, now.ctypes.data)
    return now[0] * 1_000_000_000 + now[1]


@dataclass
class ProbeResult:
    """The probe's waits for the GIL, µs, and where the watched thread stood for long ones."""

    gil_wait_us: np.ndarray
    culprits: list[tuple[float, str]] = field(default_factory=list)

    def summary(self) -> dict[str, float]:
        w = self.gil_wait_us
        if len(w) == 0:
            return {"wakeups": 0}
        return {"wakeups": len(w), "p50_us": round(float(np.median(w)), 1),
                "p99_us": round(float(np.percentile(w, 99)), 1),
                "max_us": round(float(w.max()), 1), "over_100us": int((w > 100).sum()),
                "over_1ms": int((w > 1000).sum()), "total_over_100us_ms":
                    round(float(w[w > 100].sum()) / 1e3, 1)}

    def by_place(self) -> list[tuple[str, int, float]]:
        """(place, long waits, worst µs) per place, most total wait first."""
        count: Counter[str] = Counter()
        worst: dict[str, float] = {}
        total: Counter[str] = Counter()
        for wait, place in self.culprits:
            count[place] += 1
            total[place] += wait
            worst[place] = max(worst.get(place, 0.0), wait)
        return [(p, count[p], worst[p]) for p, _ in total.most_common()]


class GilProbe:
    """Use as a context manager around the work to watch; ``result`` afterwards.

    Args:
        watched: the thread whose position is recorded on long waits (default the thread
            that creates the probe).
        period_s: the probe's sleep.
        report_s: waits longer than this record the watched thread's position.
        depth: stack frames kept per position.
    """

    def __init__(self, watched: threading.Thread | None = None, period_s: float = 100e-6,
                 report_s: float = 100e-6, depth: int = 4) -> None:
        self._watched = (watched or threading.current_thread()).ident
        self._timespec = np.array(divmod(int(period_s * 1e9), 1_000_000_000), dtype=np.int64)
        self._report_ns = int(report_s * 1e9)
        self._depth = depth
        self._stop = threading.Event()
        self._waits: list[int] = []
        self._culprits: list[tuple[float, str]] = []
        self._thread = threading.Thread(target=self._run, name="gil-probe", daemon=True)
        self.result: ProbeResult | None = None
        _nap(self._timespec, np.zeros(2, dtype=np.int64))  # compile before watching

    def _run(self) -> None:
        clock = time.perf_counter_ns
        timespec, now = self._timespec, np.zeros(2, dtype=np.int64)
        waits, culprits, report_ns = self._waits, self._culprits, self._report_ns
        while not self._stop.is_set():
            woke = _nap(timespec, now)
            wait = clock() - woke
            waits.append(wait)
            if wait > report_ns:
                frame = sys._current_frames().get(self._watched)
                place = "(not running)" if frame is None else " < ".join(
                    f"{fs.name}@{fs.filename.rsplit('/', 1)[-1]}:{fs.lineno}"
                    for fs in reversed(traceback.extract_stack(frame, self._depth)))
                culprits.append((wait / 1e3, place))

    def __enter__(self) -> GilProbe:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.result = ProbeResult(np.array(self._waits, dtype=np.float64) / 1e3,
                                  self._culprits)
