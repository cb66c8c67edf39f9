"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import gc
import os
import platform
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Timing:
    """Per-call wall times, µs."""

    median_us: float
    p99_us: float
    samples: int


def time_calls(calls: list[Callable[[], object]], repeats: int) -> Timing:
    """Time each call in ``calls`` ``repeats`` times (round-robin), one sample per call."""
    samples = np.empty(repeats * len(calls), dtype=np.int64)
    clock = time.perf_counter_ns
    i = 0
    with _quiet_gc():
        for _ in range(repeats):
            for call in calls:
                t0 = clock()
                call()
                samples[i] = clock() - t0
                i += 1
    us = samples / 1e3
    return Timing(float(np.median(us)), float(np.percentile(us, 99)), len(us))


@contextmanager
def _quiet_gc():
    enabled = gc.isenabled()
    gc.collect()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def machine_line() -> str:
    """One line describing where a benchmark ran."""
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{platform.system()} {platform.release()}")
