"""``burrforce device test``: open a device, home it, render a gentle spring to the workspace
centre for a few seconds, and report the servo rate, period jitter and what was read.

No server is involved: this checks the device, its permissions, its firmware and its servo
rate on its own, before a session depends on it.
"""

from __future__ import annotations

import signal
import time
from collections.abc import Callable

import numpy as np

from ..haptics.limits import limit_force
from .base import DeviceState
from .registry import create_device, parse_spec

#: The spring's share of the device's rated stiffness and damping: gentle, clearly felt.
SPRING_SHARE = 0.1
#: Its force never exceeds this share of the device's maximum, and fades in over RAMP_S (a
#: grip left far from the centre after homing must not be yanked back).
FORCE_SHARE = 0.25
RAMP_S = 1.0


#: The servo is said to miss its rating below this share of the rated rate, or when its
#: period's p99 exceeds ``JITTER_P99`` rated periods or its longest ``JITTER_MAX`` of them.
RATE_SHARE = 0.95
JITTER_P99 = 2.0
JITTER_MAX = 10.0


def servo_warnings(rate_hz: float | None, rated_hz: float, p99_us: float | None,
                   max_us: float | None) -> list[str]:
    """What the measured servo loop missed of the device's rating, in words (none: kept)."""
    if not rate_hz or rated_hz <= 0:
        return []
    period_us = 1e6 / rated_hz
    found = []
    if rate_hz < RATE_SHARE * rated_hz:
        found.append(f"the servo ran at {rate_hz:.0f} Hz, below the device's rated "
                     f"{rated_hz:g} Hz: the machine is busy or slow for this device (close "
                     "other work; serve --realtime gives the device loop a real-time priority)")
    if p99_us is not None and p99_us > JITTER_P99 * period_us:
        found.append(f"the servo period's p99 is {p99_us:.0f} µs, over {JITTER_P99:g}× the "
                     f"rated {period_us:.0f} µs: the force will feel rough")
    if max_us is not None and max_us > JITTER_MAX * period_us:
        found.append(f"the longest servo period was {max_us / 1e3:.1f} ms ({max_us / period_us:.0f}"
                     " rated periods): a stall a hand can feel")
    return found


def run_selftest(spec: str, seconds: float = 5.0, home: bool = True,
                 home_timeout_s: float = 60.0,
                 say: Callable[[str], None] = print) -> dict:
    """Run the test; returns the report (JSON-ready). The force is zero again on return,
    also after Ctrl-C or an error (``device.close``)."""
    name, options = parse_spec(spec)
    simulated = name == "sim"
    if simulated and "hand" not in options:
        # A simulated hand that held still would show a spring that never pulls.
        spec = f"{spec.strip()}{',' if ':' in spec else ':'}hand=circle"
    device = create_device(spec)
    stop = {"now": False}

    def on_signal(signum, frame) -> None:
        stop["now"] = True

    previous = signal.signal(signal.SIGINT, on_signal)
    report: dict = {"device": spec}
    try:
        device.open()
        info = device.info
        report["info"] = info.as_dict()
        say(f"opened {info.model} ({info.backend}); servo {info.servo_rate_hz:g} Hz, max force "
            f"{info.limits.max_force_N:g} N, workspace radius {info.workspace_radius_mm:g} mm")
        if home:
            say("homing...")
            if not device.home(home_timeout_s, progress=say):
                raise RuntimeError(f"not homed within {home_timeout_s:g} s: move the grip "
                                   "slowly through its whole range and try again")
            say("homed")
        k = SPRING_SHARE * info.limits.max_stiffness_N_mm
        b = SPRING_SHARE * info.limits.max_damping_N_s_mm
        who = ("the simulated hand moves the grip: watch the force follow it" if simulated
               else "move the grip to feel it")
        say(f"rendering a gentle spring to the workspace centre ({k:.3g} N/mm, at most "
            f"{FORCE_SHARE * info.limits.max_force_N:.3g} N, fading in over {RAMP_S:g} s) for "
            f"{seconds:g} s: {who} (Ctrl-C stops)")
        device.cycle(np.zeros(3))  # the first cycle loads compiled kernels: not timed
        period = 1.0 / info.servo_rate_hz
        cap_N = FORCE_SHARE * info.limits.max_force_N
        force = np.zeros(3)
        periods: list[float] = []
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        peak = 0.0
        buttons_seen = 0
        last: DeviceState | None = None
        t0 = time.monotonic()
        deadline = t0
        t_prev = None
        next_print = t0 + 1.0
        while not stop["now"] and time.monotonic() - t0 < seconds:
            state = device.cycle(force)
            now = time.monotonic()
            if t_prev is not None:
                periods.append(now - t_prev)
            t_prev = now
            last = state
            lo = np.minimum(lo, state.position_mm)
            hi = np.maximum(hi, state.position_mm)
            buttons_seen |= state.buttons
            spring = -k * state.position_mm - b * state.velocity_mm_s
            spring *= min((now - t0) / RAMP_S, 1.0)
            if np.isfinite(spring).all():
                limit_force(spring, force, cap_N, info.limits.max_slew_N_s * period)
                force = spring
            else:
                force = np.zeros(3)
            peak = max(peak, float(np.linalg.norm(force)))
            if now >= next_print:
                p = state.position_mm
                say(f"  x {p[0]:7.2f} y {p[1]:7.2f} z {p[2]:7.2f} mm   |F| "
                    f"{np.linalg.norm(force):5.2f} N   buttons {state.buttons:#x}")
                next_print += 1.0
            deadline += period
            late = time.monotonic() - deadline
            if late < 0.0:
                time.sleep(-late)
            elif late > 0.5 * period:
                deadline = time.monotonic()
        elapsed = time.monotonic() - t0
        us = np.array(periods) * 1e6
        report.update({
            "cycles": len(periods) + (1 if last is not None else 0),
            "seconds": elapsed,
            "servo_rate_hz": (len(periods) / elapsed) if elapsed > 0 else None,
            "period_p50_us": float(np.percentile(us, 50)) if len(us) else None,
            "period_p99_us": float(np.percentile(us, 99)) if len(us) else None,
            "period_max_us": float(us.max()) if len(us) else None,
            "range_mm": {"min": lo.tolist(), "max": hi.tolist()} if last is not None else None,
            "peak_force_N": peak,
            "buttons_seen": buttons_seen,
        })
        report["warnings"] = servo_warnings(report["servo_rate_hz"], info.servo_rate_hz,
                                            report["period_p99_us"], report["period_max_us"])
        return report
    finally:
        signal.signal(signal.SIGINT, previous)
        device.close()
