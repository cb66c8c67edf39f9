"""A volume's value range and histogram, gathered in one pass over its blocks."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .kernels import add_histogram, scan_values
from .slabs import VoxelSource

#: Label values must span less than this (the histogram is that long).
MAX_LABEL_SPAN = 1 << 24


def flat(values: np.ndarray) -> tuple[np.ndarray, str]:
    """``values`` as one flat run in memory order (a view when it is contiguous), and the
    order ("C" or "F") that reshapes a flat result back to ``values``' shape."""
    order = "F" if values.flags.f_contiguous and not values.flags.c_contiguous else "C"
    return values.ravel(order=order), order


def integer_view(values: np.ndarray) -> np.ndarray:
    """Booleans as uint8 (the kernels and NumPy's min/max read numbers)."""
    return values.view(np.uint8) if values.dtype == np.bool_ else values


class ValueStats:
    """The range of a source's values and, for integral values, their histogram — each
    gathered in one pass over the source when first asked for.

    Args:
        source: the values.
        counts: also gather the histogram (label maps and kind detection need it).
        progress: called as progress(values done, values) during the pass.
    """

    def __init__(self, source: VoxelSource, counts: bool = True,
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.source = source
        self.want_counts = counts
        self.progress = progress
        self._summary: tuple[float, float, bool, bool] | None = None
        self._counts: np.ndarray | None = None
        self._counts_lo = 0
        self._counts_ok = counts

    def scan(self) -> tuple[float, float, bool, bool]:
        """(min, max, all integers, all finite) over the finite values."""
        if self._summary is None:
            self._gather()
        return self._summary  # type: ignore[return-value]

    def summary(self) -> tuple[float, float, bool]:
        """(min, max, all integers); ValueError for NaN or ±Inf."""
        lo, hi, integral, finite = self.scan()
        if not finite:
            raise ValueError("the volume holds NaN or infinite values")
        return lo, hi, integral

    def counts(self) -> np.ndarray:
        """Voxels per integer value from min to max (int64). Only for integral, finite
        values spanning less than MAX_LABEL_SPAN (the callers check those first)."""
        lo, hi, integral = self.summary()
        if not (integral and self._counts_ok and self._counts is not None):
            raise ValueError("no histogram of these values")  # a caller's mistake
        start = int(lo) - self._counts_lo
        return self._counts[start:start + int(hi) - int(lo) + 1]

    def _gather(self) -> None:
        lo, hi, integral, finite = np.inf, -np.inf, True, True
        done, total = 0, self.source.size
        for _, block in self.source.blocks():
            values, _ = flat(integer_view(block))
            if values.size == 0:
                continue
            if np.issubdtype(values.dtype, np.integer):
                b_lo, b_hi, b_int, b_fin = float(values.min()), float(values.max()), True, True
            else:
                b_lo, b_hi, b_int, b_fin = scan_values(values)
            lo, hi = min(lo, b_lo), max(hi, b_hi)
            integral, finite = integral and b_int, finite and b_fin
            if self._counts_ok:
                self._count(values, b_lo, b_hi, b_int and b_fin)
            done += values.size
            if self.progress is not None:
                self.progress(done, total)
        self._summary = (lo, hi, integral, finite)

    def _count(self, values: np.ndarray, b_lo: float, b_hi: float, countable: bool) -> None:
        """Add a block to the histogram, growing it to the block's range; give the histogram
        up for good once values are not integral or span too much."""
        if not countable or b_lo > b_hi:
            self._counts_ok = countable and self._counts_ok
            return
        b_lo_i, b_hi_i = int(b_lo), int(b_hi)
        if self._counts is None:
            lo_i, hi_i = b_lo_i, b_hi_i
        else:
            lo_i = min(self._counts_lo, b_lo_i)
            hi_i = max(self._counts_lo + len(self._counts) - 1, b_hi_i)
        if hi_i - lo_i + 1 > MAX_LABEL_SPAN:
            self._counts_ok, self._counts = False, None
            return
        if self._counts is None or lo_i != self._counts_lo or \
                hi_i - lo_i + 1 != len(self._counts):
            grown = np.zeros(hi_i - lo_i + 1, dtype=np.int64)
            if self._counts is not None:
                at = self._counts_lo - lo_i
                grown[at:at + len(self._counts)] = self._counts
            self._counts, self._counts_lo = grown, lo_i
        add_histogram(values, self._counts_lo, self._counts)
