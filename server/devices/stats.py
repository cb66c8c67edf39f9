"""The device loop's statistics: one shared float64 array the loop writes and the control
plane reads (no lock: each slot is one aligned 8-byte store, and a reader that sees a counter
one cycle old loses nothing).

Layout: scalar slots (``ST_*``), then histograms of 10 µs bins, each ``HIST_BINS`` bins plus
one for everything longer: the servo period; the round trip (a pose's sampling to the loop
reading its reply); pose-to-force (a pose's sampling to the device being sent the first force
rendered from its reply); the device's I/O per cycle; and the loop's own work per cycle
(everything but the I/O, waiting for the reply and sleeping).
"""

from __future__ import annotations

import numpy as np

STATES = ("starting", "homing", "running", "stopped", "failed")
ST_STATE = 0  # index into STATES
ST_CYCLES = 1
ST_OVERRUNS = 2  # cycles that started more than half a period late
ST_SATURATED = 3  # cycles whose force the force or slew limit changed
ST_TRIPS = 4  # watchdog trips: the coupling model went stale (or none came)
ST_LIVE = 5  # 1 while a fresh model is rendered
ST_SENT = 6  # POSEs sent
ST_REPLIES = 7  # good replies used
ST_ERROR_REPLIES = 8
ST_NOTICES = 9
ST_REFUSED = 10  # sends/receives refused (nothing listens on the server's port)
ST_PASSIVITY = 11  # cycles the passivity controller added damping
ST_T_START = 12  # s, monotonic: when the servo loop started
ST_T_LAST = 13  # s, monotonic: the last cycle
ST_POSITION = 14  # 3 × mm, server frame
ST_FORCE = 17  # 3 × N, server frame: the force commanded
ST_VIB_AMPLITUDE = 20  # N
ST_VIB_FREQUENCY = 21  # Hz
ST_BUTTONS = 22
ST_LAST_NOTICE = 23  # error code of the last NOTICE (0: none)
ST_T_LAST_REPLY = 25  # s, monotonic: arrival of the newest good reply
ST_MODEL_AGE = 26  # s: age of the model rendered last cycle
ST_T_DEVICE_ZERO = 27  # s, monotonic: when the device was last sent zero after a force
ST_BAD_READINGS = 28  # non-finite positions or velocities from the device
N_SCALARS = 32

HIST_BIN_US = 10.0
HIST_BINS = 2000  # 20 ms; one more bin holds everything longer
HIST_PERIOD = N_SCALARS
HIST_RTT = HIST_PERIOD + HIST_BINS + 1
HIST_LATENCY = HIST_RTT + HIST_BINS + 1
HIST_IO = HIST_LATENCY + HIST_BINS + 1
HIST_WORK = HIST_IO + HIST_BINS + 1
N_SLOTS = HIST_WORK + HIST_BINS + 1

COUNTERS = {"cycles": ST_CYCLES, "overruns": ST_OVERRUNS, "saturations": ST_SATURATED,
            "watchdog_trips": ST_TRIPS, "poses_sent": ST_SENT, "replies": ST_REPLIES,
            "error_replies": ST_ERROR_REPLIES, "notices": ST_NOTICES, "refused": ST_REFUSED,
            "passivity_cycles": ST_PASSIVITY, "bad_readings": ST_BAD_READINGS}


def hist_add(stats: np.ndarray, base: int, value_us: float) -> None:
    i = int(value_us / HIST_BIN_US)
    stats[base + (i if 0 <= i < HIST_BINS else HIST_BINS)] += 1.0


def hist_percentiles(counts: np.ndarray, qs=(50.0, 99.0)) -> list[float | None]:
    """Percentiles (µs, bin centres; the overflow bin reads as its lower edge) of a histogram
    of HIST_BINS + 1 counts; None when it is empty."""
    total = float(counts.sum())
    if total <= 0.0:
        return [None for _ in qs]
    cumulative = np.cumsum(counts)
    out: list[float | None] = []
    for q in qs:
        i = int(np.searchsorted(cumulative, total * q / 100.0, side="left"))
        out.append(HIST_BIN_US * (i + (0.5 if i < HIST_BINS else 0.0)))
    return out


def summary(stats: np.ndarray) -> dict:
    """The statistics as JSON-ready values."""
    s = stats
    state = STATES[int(s[ST_STATE])] if 0 <= int(s[ST_STATE]) < len(STATES) else "unknown"
    running_s = max(s[ST_T_LAST] - s[ST_T_START], 0.0)
    p50, p99 = hist_percentiles(s[HIST_PERIOD:HIST_PERIOD + HIST_BINS + 1])
    r50, r99 = hist_percentiles(s[HIST_RTT:HIST_RTT + HIST_BINS + 1])
    f50, f99 = hist_percentiles(s[HIST_LATENCY:HIST_LATENCY + HIST_BINS + 1])
    i50, i99 = hist_percentiles(s[HIST_IO:HIST_IO + HIST_BINS + 1])
    w50, w99 = hist_percentiles(s[HIST_WORK:HIST_WORK + HIST_BINS + 1])
    return {
        "state": state,
        "counters": {name: int(s[i]) for name, i in COUNTERS.items()},
        "servo_rate_hz": float(s[ST_CYCLES] / running_s) if running_s > 0.0 else None,
        "period_p50_us": p50, "period_p99_us": p99,
        "round_trip_p50_us": r50, "round_trip_p99_us": r99,
        "pose_to_force_p50_us": f50, "pose_to_force_p99_us": f99,
        "device_io_p50_us": i50, "device_io_p99_us": i99,
        "loop_work_p50_us": w50, "loop_work_p99_us": w99,
        "live": bool(s[ST_LIVE]),
        "position_mm": [float(x) for x in s[ST_POSITION:ST_POSITION + 3]],
        "force_N": [float(x) for x in s[ST_FORCE:ST_FORCE + 3]],
        "vibration": {"amplitude_N": float(s[ST_VIB_AMPLITUDE]),
                      "frequency_hz": float(s[ST_VIB_FREQUENCY])},
        "buttons": int(s[ST_BUTTONS]),
        "model_age_ms": float(s[ST_MODEL_AGE]) * 1e3,
        "last_notice": int(s[ST_LAST_NOTICE]) or None,
    }
