"""Per-tick arrays reduced for a report: time per tick, runs of a state, a plot-sized series."""

from __future__ import annotations

import numpy as np

#: s. A longer silence between two ticks is a gap in the stream, not time spent cutting or
#: pushing: the session resets its velocity estimate after the same silence
#: (``SessionConfig.gap_s``).
MAX_TICK_S = 0.05
#: Points of the force series a report keeps for its plot.
MAX_SERIES_POINTS = 2000


def tick_durations_s(t_s: np.ndarray, max_tick_s: float = MAX_TICK_S) -> np.ndarray:
    """How long each tick stands for, s: until the next tick; before a gap (a silence longer
    than ``max_tick_s``) the stream's median tick period, at most ``max_tick_s``; the last
    tick 0, so that without gaps the durations add up to the span ``t_s[-1] − t_s[0]``.

    Args:
        t_s: tick times, s, shape (n,), non-decreasing.
    Returns:
        float64 (n,).
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    out = np.zeros(len(t_s))
    if len(t_s) > 1:
        step = np.diff(t_s)
        typical = min(float(np.median(step)), max_tick_s)
        out[:-1] = np.where(step <= max_tick_s, step, typical)
    return out


def runs(t_s: np.ndarray, mask: np.ndarray, dt_s: np.ndarray,
         merge_s: float = 0.0) -> list[tuple[float, float]]:
    """The stretches of time where ``mask`` holds, as (start_s, end_s), in order. A run ends
    where its last tick's duration ends; runs closer than ``merge_s`` become one, which bounds
    their number by the span over ``merge_s`` (a plot cannot show narrower gaps anyway).

    Args:
        t_s, dt_s: tick times and durations (``tick_durations_s``), s, shape (n,).
        mask: bool (n,).
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return []
    edges = np.diff(np.concatenate(([0], mask.view(np.int8), [0])))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1  # last tick of each run
    out: list[tuple[float, float]] = []
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        start, end = float(t_s[a]), float(t_s[b] + dt_s[b])
        if out and start - out[-1][1] < merge_s:
            out[-1] = (out[-1][0], max(out[-1][1], end))
        else:
            out.append((start, end))
    return out


def downsample_min_max(t_s: np.ndarray, y: np.ndarray, limit: int = MAX_SERIES_POINTS,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """At most ``limit`` points of the series (t_s, y) that keep its peaks: the ticks are cut
    into ``limit // 2`` bins of equal count and each bin keeps its smallest and its largest
    value, in time order. A mean per bin would shave a 1 ms force spike off a 10 min plot.

    Args:
        t_s: times, s, shape (n,), ascending.
        y: values, shape (n,).
        limit: ≥ 2.
    Returns:
        (t_s, y) copies, float64, ascending in time; the series itself if n ≤ limit.
    """
    if limit < 2:
        raise ValueError(f"limit must be at least 2, got {limit}")
    t_s = np.asarray(t_s, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n = len(y)
    if n <= limit:
        return t_s.copy(), y.copy()
    bins = limit // 2
    edges = np.linspace(0, n, bins + 1).astype(np.int64)  # n > bins: no bin is empty
    keep = np.empty(2 * bins, dtype=np.int64)
    for b in range(bins):
        lo, hi = int(edges[b]), int(edges[b + 1])
        part = y[lo:hi]
        keep[2 * b] = lo + int(np.argmin(part))
        keep[2 * b + 1] = lo + int(np.argmax(part))
    keep = np.unique(keep)  # sorted; a flat bin's min and max may be the same tick
    return t_s[keep], y[keep]
