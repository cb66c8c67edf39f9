"""An FTDI FT232-class USB–serial bridge, as the host sees it over USB.

What the chip does (FTDI application notes AN232B-04 "Data throughput, latency and
handshaking", AN232B-05 "Configuring FT232R, FT2232 and FT232B baud rates"; the request
numbers are libftdi's/libnifalcon's, restated in ``falcon.protocol``):

- vendor OUT requests on endpoint 0 set it up: reset/purge, modem lines (DTR, RTS), flow
  control, baud divisor, line format, latency timer;
- bytes the host writes to bulk OUT go out on the serial line at the set baud
  (:meth:`EmulatedFtdi.serial_from_host`: the serial side, a subclass's job);
- bytes the serial side answers (:meth:`EmulatedFtdi.serial_to_host`) are buffered and
  returned on bulk IN, **every** IN packet starting with two modem-status bytes; with an
  empty buffer the chip still answers a status-only packet each latency-timer period.

With ``latency=True`` buffered data also waits for the latency timer (or a full packet) as on
the real chip; by default it is returned at once, which keeps emulated cycles fast.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from burrforce.server.devices.falcon import protocol as fp

from .function import DIR_IN, TYPE_MASK, TYPE_VENDOR, EmulatedFunction, Endpoint

#: Modem status: byte 0 = CTS | DSR | bit 0 (always set), byte 1 = THRE | TEMT (idle line).
MODEM_STATUS = bytes((0x31, 0x60))
SIO_GET_MODEM_STATUS = 5
SIO_SET_EVENT_CHAR = 6
SIO_SET_ERROR_CHAR = 7
SIO_GET_LATENCY_TIMER = 10
SIO_SET_BITMODE = 11
SIO_READ_EEPROM = 0x90
DTR_BIT = 0x01
RTS_BIT = 0x02
#: Baud = 3 MHz / divisor; the divisor's 3-bit fraction code → eighths (AN232B-05).
FTDI_CLOCK_HZ = 3_000_000
_FRACTION_EIGHTHS = (0, 4, 2, 1, 3, 5, 6, 7)


def divisor_to_baud(divisor: int) -> float:
    """The baud rate (Bd) an FTDI divisor sets. ``divisor`` = wValue | (wIndex bit 0) << 16:
    a 14-bit integer part and a 3-bit fraction code (bits 14-16); integer 0 means 3 MBd and
    integer 1 (code 0) 2 MBd."""
    integer = divisor & 0x3FFF
    code = (divisor >> 14) & 0x7
    if integer == 0:
        return float(FTDI_CLOCK_HZ)
    if integer == 1 and code == 0:
        return FTDI_CLOCK_HZ * 2.0 / 3.0
    return FTDI_CLOCK_HZ / (integer + _FRACTION_EIGHTHS[code] / 8.0)


def same_baud(divisor_a: int, divisor_b: int, tolerance: float = 0.03) -> bool:
    """Whether two divisors set baud rates a UART accepts as equal (within ``tolerance``)."""
    a, b = divisor_to_baud(divisor_a), divisor_to_baud(divisor_b)
    return abs(a - b) <= tolerance * b


class EmulatedFtdi(EmulatedFunction):
    """An FT232BM-class bridge: interface 0, bulk IN 0x81, bulk OUT 0x02, 64-byte packets.

    Attributes the serial side reads: ``baud_divisor``, ``line`` (SIO_SET_DATA wValue),
    ``dtr``, ``rts``, ``latency_ms``, ``flow``; ``events`` counts purges and DTR edges.
    """

    bcd_device = 0x0400
    max_packet_ep0 = 8
    interface_class = 0xFF
    interface_subclass = 0xFF
    interface_protocol = 0xFF
    max_power_mA = 100
    endpoints = (Endpoint(fp.EP_IN), Endpoint(fp.EP_OUT))

    def __init__(self, latency: bool = False, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.clock = clock
        self.emulate_latency = bool(latency)
        self.to_host = bytearray()
        self._chip_power_on()

    def _chip_power_on(self) -> None:
        self.to_host.clear()
        self.baud_divisor = fp.BAUD_DIVISOR_9600
        self.line = fp.LINE_8N1
        self.flow = fp.FLOW_CONTROL_OFF
        self.dtr = False
        self.rts = False
        self.latency_ms = fp.LATENCY_FIRMWARE_MS
        self.events: dict[str, int] = {"purge_rx": 0, "purge_tx": 0, "dtr_rise": 0,
                                       "dtr_fall": 0}
        self._last_in_ns = self.clock()
        self._first_buffered_ns: int | None = None

    def power_cycle(self) -> None:
        self._chip_power_on()

    # -- the serial side (subclasses) ---------------------------------------------------

    def serial_from_host(self, data: bytes) -> None:
        """Bytes the host sent, as they go out on the serial line (default: nobody listens)."""

    def serial_to_host(self, data: bytes) -> None:
        """Queue bytes the serial side answers; the host reads them on bulk IN."""
        if data:
            if not self.to_host:
                self._first_buffered_ns = self.clock()
            self.to_host += data
            self.wake()

    def on_dtr(self, level: bool) -> None:
        """DTR changed to ``level`` (subclasses: e.g. a microcontroller reset line)."""

    def on_purge_tx(self) -> None:
        """The host purged the chip's TX buffer (bytes on their way to the serial side)."""

    # -- USB -----------------------------------------------------------------------------

    def control(self, request_type: int, request: int, value: int, index: int,
                data_or_length: bytes | int) -> bytes | int | None:
        if request_type & TYPE_MASK != TYPE_VENDOR:
            return super().control(request_type, request, value, index, data_or_length)
        if request_type & DIR_IN:
            if request == SIO_GET_MODEM_STATUS:
                return MODEM_STATUS
            if request == SIO_GET_LATENCY_TIMER:
                return bytes((self.latency_ms,))
            if request == SIO_READ_EEPROM:
                return b"\x00\x00"   # a blank EEPROM word
            return None
        if request == fp.SIO_RESET:
            if value in (fp.SIO_RESET_SIO, fp.SIO_RESET_PURGE_RX):
                self.to_host.clear()
                self._first_buffered_ns = None
                self.events["purge_rx"] += 1
            if value in (fp.SIO_RESET_SIO, fp.SIO_RESET_PURGE_TX):
                self.events["purge_tx"] += 1
                self.on_purge_tx()
            return 0 if value in (0, 1, 2) else None
        if request == fp.SIO_MODEM_CTRL:
            mask, level = value >> 8, value & 0xFF
            if mask & RTS_BIT:
                self.rts = bool(level & RTS_BIT)
            if mask & DTR_BIT:
                new = bool(level & DTR_BIT)
                if new != self.dtr:
                    self.dtr = new
                    self.events["dtr_rise" if new else "dtr_fall"] += 1
                    self.on_dtr(new)
            return 0
        if request == fp.SIO_SET_FLOW_CTRL:
            self.flow = value
            return 0
        if request == fp.SIO_SET_BAUD_RATE:
            self.baud_divisor = value | ((index & 0x1) << 16)
            return 0
        if request == fp.SIO_SET_DATA:
            self.line = value
            return 0
        if request == fp.SIO_SET_LATENCY_TIMER:
            if not 1 <= value <= 255:
                return None
            self.latency_ms = value
            return 0
        if request in (SIO_SET_EVENT_CHAR, SIO_SET_ERROR_CHAR, SIO_SET_BITMODE):
            return 0
        return None

    def out(self, endpoint: int, data: bytes) -> None:
        self.serial_from_host(data)

    def in_(self, endpoint: int, max_len: int) -> bytes | None:
        now = self.clock()
        latency_ns = self.latency_ms * 1_000_000
        payload_per_packet = fp.USB_PACKET_BYTES - fp.FTDI_STATUS_BYTES
        if self.to_host:
            ready = (not self.emulate_latency or len(self.to_host) >= payload_per_packet
                     or now - (self._first_buffered_ns or now) >= latency_ns)
            if ready and max_len >= fp.FTDI_STATUS_BYTES:
                out = bytearray()
                while self.to_host and max_len - len(out) > fp.FTDI_STATUS_BYTES:
                    room = min(payload_per_packet, max_len - len(out) - fp.FTDI_STATUS_BYTES)
                    out += MODEM_STATUS + self.to_host[:room]
                    del self.to_host[:room]
                self._first_buffered_ns = now if self.to_host else None
                self._last_in_ns = now
                return bytes(out)
        if now - self._last_in_ns >= latency_ns:
            self._last_in_ns = now
            return MODEM_STATUS[:max_len]
        return None

    def ftdi_state(self) -> dict[str, Any]:
        return {"baud_divisor": self.baud_divisor,
                "baud": round(divisor_to_baud(self.baud_divisor), 1),
                "line": self.line, "flow": self.flow, "dtr": self.dtr, "rts": self.rts,
                "latency_ms": self.latency_ms, "buffered_to_host": len(self.to_host),
                "events": dict(self.events)}
