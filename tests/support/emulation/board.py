"""An emulated burrforce vibration board (``actuators.board_protocol``), byte for byte.

Behaviour is the protocol module's "Board behaviour" list: each OUT packet is one frame,
decoded with ``board_protocol.decode_frame`` (checked in the board's order); a valid frame
takes effect at once (the output ramps linearly over ``RAMP_MAX_MS``) and refreshes the TTL
watchdog; a bad one changes nothing, counts in ``rejected`` and latches its fault bit; after
every OUT packet one status is queued on EP_IN, replacing an unread one, and latched faults
clear once a status carrying them has been read. With no status queued the IN endpoint NAKs
(the host's read stays pending until it times out).

The watchdog is evaluated whenever the board is touched (a packet, a poll, a control
command), and an expiry is recorded at the exact time it happened (last valid frame +
``ttl_ms``), so a test can check "silent within the TTL" without a timer thread.

Recorded for the control channel, each with its arrival time (``time.monotonic_ns``): every
frame received (raw bytes, decoded fields or the rejection), and every output change
(``output_log``: the amplitude/frequency the board ramps to, and why).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from burrforce.server.devices.actuators import board_protocol as bp

from .function import EmulatedFunction, Endpoint, Stall

LEVEL_WINDOW_NS = 10_000_000     # the status's level: peak over the last ≥ 10 ms
RAMP_NS = bp.RAMP_MAX_MS * 1_000_000
INJECTABLE_FAULTS = bp.FAULT_AMP_FAULT | bp.FAULT_OVERTEMP | bp.FAULT_UNDERRUN


class EmulatedBoard(EmulatedFunction):
    """The emulated vibration board.

    Args:
        log_rows: frames (and output changes) kept for the control channel.
        serial: the USB serial-number string.
    """

    vendor_id = bp.VID
    product_id = bp.PID
    manufacturer = bp.MANUFACTURER
    product = bp.PRODUCT
    interface_class = bp.INTERFACE_CLASS
    interface_subclass = 0x00
    interface_protocol = 0x00
    endpoints = (Endpoint(bp.EP_OUT, max_packet=bp.MAX_PACKET_SIZE),
                 Endpoint(bp.EP_IN, max_packet=bp.MAX_PACKET_SIZE))

    def __init__(self, log_rows: int = 100_000, serial: str = "EMUBOARD1",
                 clock: Callable[[], int] = time.monotonic_ns) -> None:
        if not 100 <= int(log_rows) <= 10_000_000:
            raise ValueError(f"log_rows must be 100..10 000 000, got {log_rows}")
        self.serial = serial
        self.clock = clock
        self.frames: deque[dict[str, Any]] = deque(maxlen=int(log_rows))
        self.output_log: deque[dict[str, Any]] = deque(maxlen=int(log_rows))
        self._power_on()

    def _power_on(self) -> None:
        self.frame: bp.Frame | None = None       # the last accepted frame
        self.last_valid_ns: int | None = None
        self.ttl_expired = False
        self.last_seq = 0
        self.latched_faults = 0
        self.underruns = 0
        self.rejected = 0
        self.status_queued = False
        self.statuses_sent = 0
        self.frames_received = 0
        self.min_interval_ns: int | None = None
        self._last_frame_ns: int | None = None
        # Output level (Q15) as (t_ns, level) corners, linear in between: each ramp adds a
        # start and an end corner RAMP_NS apart.
        self._corners: deque[tuple[int, float]] = deque()
        self._output_key: tuple[int, int, bool] = (0, 0, False)

    def power_off(self) -> None:
        if self._output_key[0]:
            self._ramp(self.clock(), 0, "power off")

    def power_cycle(self) -> None:
        """Power-up state: silent, counters zero (the frame and output logs are kept)."""
        self._power_on()

    # -- output model ----------------------------------------------------------------

    def _level_at(self, t_ns: int) -> float:
        """The output level (Q15) at ``t_ns``: piecewise linear through the corners."""
        level = 0.0
        previous: tuple[int, float] | None = None
        for t, value in self._corners:
            if t > t_ns:
                if previous is not None and previous[1] != value:
                    s = (t_ns - previous[0]) / (t - previous[0])
                    return previous[1] + s * (value - previous[1])
                return level
            level = value
            previous = (t, value)
        return level

    def _ramp(self, t_ns: int, target_q15: int, reason: str) -> None:
        self._prune(t_ns - LEVEL_WINDOW_NS)
        start = self._level_at(t_ns)
        while self._corners and self._corners[-1][0] > t_ns:
            self._corners.pop()    # a ramp cut short by a newer one
        self._corners.append((t_ns, start))
        self._corners.append((t_ns + RAMP_NS, float(target_q15)))
        f = self.frame
        key = (target_q15, f.frequency_mhz if f else 0, bool(f and f.am))
        if key != self._output_key:
            self._output_key = key
            self.output_log.append({"t_ns": t_ns, "amplitude_q15": key[0],
                                    "frequency_mhz": key[1], "am": key[2], "reason": reason})

    def _prune(self, start: int) -> None:
        """Forget corners before ``start`` except the last one at or before it."""
        while len(self._corners) > 2 and self._corners[1][0] <= start:
            self._corners.popleft()

    def _peak_level(self, now: int) -> int:
        start = now - LEVEL_WINDOW_NS
        self._prune(start)
        peak = max(self._level_at(start), self._level_at(now))
        for t, level in self._corners:
            if start <= t <= now:
                peak = max(peak, level)
        return min(bp.AMPLITUDE_Q15_MAX, round(peak))

    def _check_ttl(self, now: int) -> None:
        if self.last_valid_ns is None or self.ttl_expired or self.frame is None:
            return
        expiry = self.last_valid_ns + self.frame.ttl_ms * 1_000_000
        if now >= expiry:
            self.ttl_expired = True
            self.latched_faults |= bp.FAULT_TTL_EXPIRED
            self._ramp(expiry, 0, "ttl")

    def _output_on(self) -> bool:
        return bool(self.frame and self.frame.audible and not self.ttl_expired)

    def _state_bits(self) -> int:
        bits = 0
        if self._output_on():
            bits |= bp.STATE_OUTPUT_ON
            if self.frame.am:
                bits |= bp.STATE_AM_ACTIVE
        if self.ttl_expired:
            bits |= bp.STATE_TTL_EXPIRED
        return bits

    # -- USB -------------------------------------------------------------------------

    def out(self, endpoint: int, data: bytes) -> None:
        if endpoint != bp.EP_OUT:
            raise Stall(f"no OUT endpoint {endpoint:#04x}")
        now = self.clock()
        self._check_ttl(now)
        self.frames_received += 1
        if self._last_frame_ns is not None:
            gap = now - self._last_frame_ns
            self.min_interval_ns = gap if self.min_interval_ns is None \
                else min(self.min_interval_ns, gap)
        self._last_frame_ns = now
        record: dict[str, Any] = {"t_ns": now, "raw": data.hex()}
        try:
            frame = bp.decode_frame(data)
        except bp.ProtocolError as exc:
            self.rejected += 1
            self.latched_faults |= exc.fault
            record.update(valid=False, error=str(exc), fault=exc.fault)
        else:
            record.update(valid=True, frame=asdict(frame))
            self.frame = frame
            self.last_valid_ns = now
            self.last_seq = frame.seq
            self.ttl_expired = False
            self._ramp(now, frame.amplitude_q15 if frame.audible else 0, "frame")
        self.frames.append(record)
        self.status_queued = True

    def in_(self, endpoint: int, max_len: int) -> bytes | None:
        if endpoint != bp.EP_IN:
            raise Stall(f"no IN endpoint {endpoint:#04x}")
        now = self.clock()
        self._check_ttl(now)
        if not self.status_queued:
            return None
        self.status_queued = False
        self.statuses_sent += 1
        status = bp.encode_status(self.last_seq, self._state_bits(), self.latched_faults,
                                  self.underruns, self.rejected, self._peak_level(now))
        self.latched_faults = 0
        return status

    # -- control channel -------------------------------------------------------------

    def _state(self) -> dict[str, Any]:
        now = self.clock()
        self._check_ttl(now)
        f = self.frame
        return {"t_ns": now, "output_on": self._output_on(), "state_bits": self._state_bits(),
                "ttl_expired": self.ttl_expired, "last_seq": self.last_seq,
                "level_q15": round(self._level_at(now)), "peak_level_q15": self._peak_level(now),
                "frame": asdict(f) if f else None, "last_valid_ns": self.last_valid_ns,
                "latched_faults": self.latched_faults, "rejected": self.rejected,
                "underruns": self.underruns, "frames_received": self.frames_received,
                "statuses_sent": self.statuses_sent, "status_queued": self.status_queued,
                "min_interval_ns": self.min_interval_ns}

    def _frames(self, since_ns: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        rows = [r for r in self.frames if r["t_ns"] > since_ns]
        return rows[-int(limit):] if limit is not None else rows

    def _output_log(self, since_ns: int = 0) -> list[dict[str, Any]]:
        self._check_ttl(self.clock())
        return [r for r in self.output_log if r["t_ns"] > since_ns]

    def _inject_fault(self, faults: int) -> int:
        faults = int(faults)
        if not faults or faults & ~INJECTABLE_FAULTS:
            raise ValueError(f"injectable faults are bits of {INJECTABLE_FAULTS:#06x} "
                             f"(amplifier fault, over-temperature, underrun), got {faults:#x}")
        if faults & bp.FAULT_UNDERRUN:
            self.underruns = (self.underruns + 1) & 0xFFFFFFFF
        self.latched_faults |= faults
        self.status_queued = True
        return self.latched_faults

    def _clear(self) -> bool:
        self.frames.clear()
        self.output_log.clear()
        return True

    def commands(self) -> dict[str, Callable[..., Any]]:
        return {"state": self._state, "frames": self._frames, "output_log": self._output_log,
                "inject_fault": self._inject_fault, "clear": self._clear}
