"""The converter's kernels over flat runs of values (a block of the volume at a time)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def scan_values(values):
    """(min, max, all integers, all finite) of a flat float array, over its finite values."""
    lo = np.inf
    hi = -np.inf
    integral = True
    finite = True
    for n in range(values.shape[0]):
        x = float(values[n])
        if not np.isfinite(x):
            finite = False
            continue
        if x < lo:
            lo = x
        if x > hi:
            hi = x
        if integral and x != np.floor(x):
            integral = False
    return lo, hi, integral, finite


@njit(cache=True, nogil=True)
def add_histogram(values, lo, counts):
    """Count each value of a flat integral array into ``counts`` (value lo at index 0)."""
    for n in range(values.shape[0]):
        counts[int(values[n]) - lo] += 1


@njit(cache=True, nogil=True)
def apply_lut(values, lo, lut, density, labels):
    """Flat arrays: each value's label from ``lut``; density 255 where it has one."""
    for n in range(values.shape[0]):
        label = lut[int(values[n]) - lo]
        labels[n] = label
        density[n] = 255 if label != 0 else 0
