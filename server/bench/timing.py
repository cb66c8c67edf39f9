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


def time_interleaved(
    groups: list[list[Callable[[], object]]], repeats: int, passes: int = 10
) -> list[Timing]:
    """Time several groups of calls in alternating passes, so that the machine's slow and fast
    spells (this machine is shared) fall evenly on every group rather than on whichever ran
    during them. Each group gets ``repeats`` rounds in all."""
    samples: list[list[np.ndarray]] = [[] for _ in groups]
    passes = max(1, min(passes, repeats))
    for n in range(passes):
        rounds = repeats // passes + (1 if n < repeats % passes else 0)
        for i, calls in enumerate(groups):
            samples[i].append(sample_calls(calls, rounds))
    return [summarize(np.concatenate(s)) for s in samples]


def sample_calls(calls: list[Callable[[], object]], repeats: int) -> np.ndarray:
    """Per-call wall times in ns, shape (repeats·len(calls),)."""
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
    return samples


def wait_until(due_s: float) -> None:
    """Return once ``time.perf_counter()`` reaches ``due_s``: sleep most of the wait, then spin
    the last 0.4 ms or so, which a sleep would overshoot (a paced stream's send times)."""
    ahead = due_s - time.perf_counter()
    if ahead > 0.0006:
        time.sleep(ahead - 0.0004)
    while time.perf_counter() < due_s:
        pass


def summarize(samples_ns: np.ndarray) -> Timing:
    us = samples_ns / 1e3
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
