"""Velocity of the tool from its position samples: First-Order Adaptive Windowing (FOAW).

Janabi-Sharifi, Hayward & Chen, "Discrete-time adaptive windowing for velocity estimation",
IEEE Trans. Control Systems Technology 8(6), 2000; the *end-fit* variant, on non-uniform
sample times (the client's timestamps, which jitter).

A plain finite difference of encoder positions is useless at haptic rates: at 1 kHz a
0.05 mm quantum turns a slow 3 mm/s stroke into a train of 0 and 50 mm/s spikes. FOAW
instead takes the longest window back from the newest sample k whose end-to-end line
``p_k − b·(t_k − t)`` with slope ``b = (p_k − p_{k−n}) / (t_k − t_{k−n})`` passes within the
position uncertainty ``d`` of every sample inside it. Slow, smooth motion gets a long window
(little noise); a sudden change breaks the line and the window shrinks at once (little lag).

The hot path calls :func:`velocity_step` once per packet: one numba call that pushes the
sample into a fixed ring and estimates, with no allocation and no Python objects. The ring
is three arrays the caller owns (see :func:`new_ring`)::

    ring_t_s    float64 (RING,)    sample times, s (strictly increasing from oldest to newest)
    ring_p_mm   float64 (RING, 3)  sample positions, mm
    ring_state  int64   (2,)       [head = index of the newest sample, count of samples]

:func:`velocity_reference` is a pure-Python statement of the same algorithm, for tests.
"""

from __future__ import annotations

import math

import numpy as np

from ..hot_kernel import hot_kernel

#: Capacity of the sample ring: the window is at most RING − 1 intervals. At 1 kHz that is
#: 31 ms, long enough to average a 0.05 mm quantum down to ~1.6 mm/s at rest, short enough
#: that the O(n²) acceptance test stays ~1.5 k flops per packet.
RING = 32

#: Slack on the acceptance band, relative to the magnitudes involved (positions, slope × time):
#: with noise_mm = 0 an exactly linear motion must still be accepted despite rounding, which
#: is a few ulps of those magnitudes; 1e-12 is ~4500 ulps, yet 1e-9 mm at a 1000 mm scale.
REL_EPS = 1e-12

# Indices into ring_state.
HEAD = 0
COUNT = 1


def new_ring(capacity: int = RING) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Empty ring arrays ``(ring_t_s (capacity,), ring_p_mm (capacity, 3), ring_state (2,))``."""
    return (np.zeros(capacity, dtype=np.float64), np.zeros((capacity, 3), dtype=np.float64),
            np.zeros(2, dtype=np.int64))


@hot_kernel
def reset(ring_state):
    """Forget every sample (e.g. when the device re-homes or the session restarts).

    ring_state: int64 (2,); only the count is cleared, the stale entries are never read.
    """
    ring_state[COUNT] = 0


@hot_kernel
def velocity_step(ring_t_s, ring_p_mm, ring_state, t_s, px, py, pz, noise_mm, max_span_s, out_v):
    """Push the sample (t_s; px,py,pz) into the ring, then estimate the velocity at it.

    ring_t_s: float64 (RING,), sample times, s. ring_p_mm: float64 (RING, 3), positions, mm.
    ring_state: int64 (2,) = [head (index of newest), count]; zeros for an empty ring.
    The ring's capacity is the length of its arrays (RING for :func:`new_ring`'s).
    t_s: sample time, s; px, py, pz: sample position, mm.
    noise_mm: the position uncertainty bound d (a whole quantization step + noise), mm, >= 0
    (a negative or NaN value counts as 0). The end-fit line runs through two *measured* samples, so
    samples each within q/2 of the truth can lie up to q off it: with d = q/2 the window
    collapses to 2 after every quantum step of a slow ramp; d = q keeps it long.
    max_span_s: the longest window, s; a window of one interval is used whatever its span
    (after a gap in the samples it is still the best estimate there is).
    out_v: float64 (3,) receives the velocity, mm/s.

    A sample whose time is not later than the newest one's (or that is not finite) is not
    pushed: the estimate is recomputed over the existing ring, so repeats and reordered
    packets cannot divide by zero.

    Returns the window used (number of intervals, >= 1), or 0 if there was no previous sample
    (out_v zeroed).
    """
    capacity = min(ring_t_s.shape[0], ring_p_mm.shape[0])
    head = ring_state[HEAD]
    count = ring_state[COUNT]
    # A state that cannot index the ring (never written, or corrupted) is an empty ring:
    # numba does not bounds-check, so reading through it would read outside the arrays.
    if count < 0 or count > capacity or head < 0 or head >= capacity:
        head = 0
        count = 0

    finite = (math.isfinite(t_s) and math.isfinite(px) and math.isfinite(py)
              and math.isfinite(pz))
    if finite and capacity > 0 and (count == 0 or t_s > ring_t_s[head]):
        head += 1
        if head == capacity:
            head = 0
        ring_t_s[head] = t_s
        ring_p_mm[head, 0] = px
        ring_p_mm[head, 1] = py
        ring_p_mm[head, 2] = pz
        if count < capacity:
            count += 1
    ring_state[HEAD] = head
    ring_state[COUNT] = count

    if count < 2:
        out_v[0] = 0.0
        out_v[1] = 0.0
        out_v[2] = 0.0
        return 0

    # A negative or NaN bound counts as 0 (NaN fails the comparison).
    d_mm = noise_mm if noise_mm > 0.0 else 0.0
    tk = ring_t_s[head]
    pkx = ring_p_mm[head, 0]
    pky = ring_p_mm[head, 1]
    pkz = ring_p_mm[head, 2]

    best_n = 0
    bx_best = 0.0
    by_best = 0.0
    bz_best = 0.0
    for n in range(1, count):
        i_n = head - n
        if i_n < 0:
            i_n += capacity
        span_s = tk - ring_t_s[i_n]
        # One interval is always taken; longer ones only within the span. `not (<=)` so a NaN
        # max_span_s stops at one interval rather than growing without limit.
        if n > 1 and not (span_s <= max_span_s):
            break
        bx = (pkx - ring_p_mm[i_n, 0]) / span_s
        by = (pky - ring_p_mm[i_n, 1]) / span_s
        bz = (pkz - ring_p_mm[i_n, 2]) / span_s
        # The band's rounding slack scales with what the residual is computed from: the
        # endpoint positions, and the slope times the time magnitude (t_k − t_j loses
        # ulps of |t| when times are far from 0).
        t_scale_s = max(abs(tk), abs(ring_t_s[i_n]))
        base_x = abs(pkx) + abs(ring_p_mm[i_n, 0]) + abs(bx) * t_scale_s
        base_y = abs(pky) + abs(ring_p_mm[i_n, 1]) + abs(by) * t_scale_s
        base_z = abs(pkz) + abs(ring_p_mm[i_n, 2]) + abs(bz) * t_scale_s
        ok = True
        for j in range(1, n):
            i_j = head - j
            if i_j < 0:
                i_j += capacity
            back_s = tk - ring_t_s[i_j]
            qx = ring_p_mm[i_j, 0]
            qy = ring_p_mm[i_j, 1]
            qz = ring_p_mm[i_j, 2]
            if (abs(qx - (pkx - bx * back_s)) > d_mm + REL_EPS * (base_x + abs(qx))
                    or abs(qy - (pky - by * back_s)) > d_mm + REL_EPS * (base_y + abs(qy))
                    or abs(qz - (pkz - bz * back_s)) > d_mm + REL_EPS * (base_z + abs(qz))):
                ok = False
                break
        if not ok:
            # FOAW stops at the first window that fails: a longer one reaching past a change
            # of velocity could pass again by chance, and would then lag.
            break
        best_n = n
        bx_best = bx
        by_best = by
        bz_best = bz

    out_v[0] = bx_best
    out_v[1] = by_best
    out_v[2] = bz_best
    return best_n


def velocity_reference(times, positions, noise_mm, max_span_s):
    """Pure-Python FOAW (end fit) at the last sample; the specification of velocity_step.

    times: sequence of N float, s, strictly increasing; positions: N × 3 floats, mm (all of
    them form the window candidates; pass the last RING to compare with the ring).
    Returns (v, n): v a tuple of 3 floats, mm/s, and n the window in intervals (0 and zero
    velocity when N < 2). The arithmetic is written in the same order as velocity_step, so the
    two agree bit for bit.
    """
    t = [float(x) for x in times]
    p = [tuple(float(c) for c in row) for row in positions]
    if len(t) != len(p):
        raise ValueError("times and positions differ in length")
    k = len(t) - 1
    if k < 1:
        return (0.0, 0.0, 0.0), 0
    d_mm = noise_mm if noise_mm > 0.0 else 0.0
    best_v, best_n = (0.0, 0.0, 0.0), 0
    for n in range(1, k + 1):
        span_s = t[k] - t[k - n]
        if n > 1 and not (span_s <= max_span_s):
            break
        b = [(p[k][a] - p[k - n][a]) / span_s for a in range(3)]
        t_scale_s = max(abs(t[k]), abs(t[k - n]))
        base = [abs(p[k][a]) + abs(p[k - n][a]) + abs(b[a]) * t_scale_s for a in range(3)]
        ok = all(
            abs(p[k - j][a] - (p[k][a] - b[a] * (t[k] - t[k - j])))
            <= d_mm + REL_EPS * (base[a] + abs(p[k - j][a]))
            for j in range(1, n) for a in range(3)
        )
        if not ok:
            break
        best_v, best_n = (b[0], b[1], b[2]), n
    return best_v, best_n


class DeviceVelocity:
    """The velocity a device driver reports: FOAW on its encoder readings (the longest window
    whose end-fit line stays within the encoder's quantum of every reading), mm/s — the same
    estimator as the hot loop's, with its ring owned here.

    Args:
        noise_mm: the readings' uncertainty (the encoder's resolution).
        max_span_s: the longest window.
    """

    def __init__(self, noise_mm: float, max_span_s: float = 0.03) -> None:
        self.ring_t, self.ring_p, self.ring_state = new_ring()
        self.noise_mm = noise_mm
        self.max_span_s = max_span_s
        self.v = np.zeros(3)
        self.t_last = -math.inf

    def update(self, x_mm, t_s: float) -> np.ndarray:
        """Push a reading taken at ``t_s`` (strictly later than the last; an equal or earlier
        one leaves the estimate as it is) and return the estimate ((3,), the same array)."""
        if t_s > self.t_last:
            velocity_step(self.ring_t, self.ring_p, self.ring_state, t_s, float(x_mm[0]),
                          float(x_mm[1]), float(x_mm[2]), self.noise_mm, self.max_span_s, self.v)
            self.t_last = t_s
        return self.v

    def reset(self) -> None:
        """Forget every reading (the device re-homed: its positions changed meaning)."""
        reset(self.ring_state)
        self.v[:] = 0.0
        self.t_last = -math.inf
