"""The report's force plot as inline SVG: no script, no matplotlib, nothing fetched."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from html import escape

import numpy as np

from .series import MAX_TICK_S

WIDTH, HEIGHT = 880, 280
LEFT, RIGHT, TOP, BOTTOM = 56, 16, 16, 40
CUT_FILL = "#dbeafe"
LINE = "#1f2937"
THRESHOLD = "#d97706"
FORBIDDEN = "#dc2626"
#: The force axis reaches at least this, N: a report of a session that never pressed on bone,
#: with a threshold of a few ulps, still has an axis (its ticks' step underflowed to 0).
MIN_FORCE_AXIS_N = 1e-3


def nice_ticks(hi: float, n: int = 5) -> list[float]:
    """Round axis ticks from 0 to at least ``hi`` (> 0), about ``n`` of them."""
    raw = hi / n
    step = 10.0 ** math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * step >= raw:
            step *= m
            break
    return [i * step for i in range(math.ceil(hi / step - 1e-9) + 1)]


def force_plot(t_s: np.ndarray, force_N: np.ndarray, threshold_N: float,
               forbidden_s: Sequence[float], cutting_s: Sequence[tuple[float, float]],
               title: str = "Hand force |F| over time") -> str:
    """An ``<svg>`` element: |F| (N) against time (s) as a polyline, the threshold as a dashed
    line, each forbidden contact as a red mark at its time, cutting stretches shaded.

    Args:
        t_s, force_N: the (downsampled) series, shape (n,).
        forbidden_s: times of forbidden contacts, s.
        cutting_s: (start_s, end_s) stretches of cutting.
    """
    t = np.asarray(t_s, dtype=np.float64)
    f = np.nan_to_num(np.asarray(force_N, dtype=np.float64), nan=0.0, posinf=0.0)
    t_max = max(float(t[-1]) if len(t) else 0.0, 1e-3)
    f_ticks = nice_ticks(max(float(f.max()) if len(f) else 0.0, threshold_N,
                             MIN_FORCE_AXIS_N) * 1.05)
    t_ticks = nice_ticks(t_max)
    x_hi, y_hi = t_ticks[-1], f_ticks[-1]
    pw, ph = WIDTH - LEFT - RIGHT, HEIGHT - TOP - BOTTOM

    def x(v: float) -> float:
        return LEFT + pw * v / x_hi

    def y(v: float) -> float:
        return TOP + ph * (1.0 - v / y_hi)

    out = [f'<svg viewBox="0 0 {WIDTH} {HEIGHT}" '
           f'role="img" class="plot"><title>{escape(title)}</title>']
    for a, b in cutting_s:
        out.append(f'<rect x="{x(a):.1f}" y="{TOP}" width="{max(x(b) - x(a), 0.5):.1f}" '
                   f'height="{ph}" fill="{CUT_FILL}"/>')
    for v in f_ticks:
        out.append(f'<line x1="{LEFT}" x2="{LEFT + pw}" y1="{y(v):.1f}" y2="{y(v):.1f}" '
                   f'stroke="#e5e7eb"/><text x="{LEFT - 6}" y="{y(v) + 4:.1f}" '
                   f'text-anchor="end">{v:g}</text>')
    for v in t_ticks:
        out.append(f'<text x="{x(v):.1f}" y="{TOP + ph + 16}" text-anchor="middle">'
                   f'{v:g}</text>')
    out.append(f'<text x="{LEFT + pw / 2:.0f}" y="{HEIGHT - 4}" text-anchor="middle">time, s'
               f'</text><text x="14" y="{TOP + ph / 2:.0f}" text-anchor="middle" '
               f'transform="rotate(-90 14 {TOP + ph / 2:.0f})">|F|, N</text>')
    for lo, hi in _segments(t):
        points = " ".join(f"{x(a):.1f},{y(b):.1f}" for a, b in
                          zip(t[lo:hi].tolist(), f[lo:hi].tolist(), strict=True))
        out.append(f'<polyline fill="none" stroke="{LINE}" stroke-width="1" '
                   f'points="{points}"/>')
    yt = y(threshold_N)
    out.append(f'<line x1="{LEFT}" x2="{LEFT + pw}" y1="{yt:.1f}" y2="{yt:.1f}" '
               f'stroke="{THRESHOLD}" stroke-dasharray="6 4"/><text x="{LEFT + pw - 4}" '
               f'y="{yt - 4:.1f}" text-anchor="end" fill="{THRESHOLD}">threshold '
               f'{threshold_N:g} N</text>')
    for s in forbidden_s:
        out.append(f'<path d="M{x(s):.1f} {TOP}v{ph}" stroke="{FORBIDDEN}" stroke-width="1.5"/>'
                   f'<path d="M{x(s) - 5:.1f} {TOP}h10l-5 8z" fill="{FORBIDDEN}"/>')
    out.append(f'<rect x="{LEFT}" y="{TOP}" width="{pw}" height="{ph}" fill="none" '
               f'stroke="#9ca3af"/></svg>')
    return "".join(out)


def _segments(t: np.ndarray) -> list[tuple[int, int]]:
    """[lo, hi) index ranges of the series without a gap in the stream: a line drawn across
    a silence would show a force nobody felt. A gap is longer than a tick may stand for and
    than a few of the series' own steps (a downsampled series steps by whole bins)."""
    if len(t) < 2:
        return [(0, len(t))]
    step = np.diff(t)
    gap = max(MAX_TICK_S, 4.0 * float(np.median(step)))
    cuts = (np.flatnonzero(step > gap) + 1).tolist()
    bounds = [0, *cuts, len(t)]
    return list(itertools.pairwise(bounds))
