"""Wire format of the burrforce vibration board (USB, vendor class), version 1.

The board is a small full-speed USB microcontroller that synthesizes the burr's vibration
itself (DDS → DAC/amplifier → voice coil): the host sends *parameters* (frequency, amplitude,
mode) at up to 1 kHz, never samples. ``docs/actuators.md`` carries the same specification as
byte tables for firmware authors; this module is its reference implementation.

Transport: interface class 0xFF, bulk OUT :data:`EP_OUT` carries one :class:`Frame` per
packet (:data:`FRAME_SIZE` bytes), bulk IN :data:`EP_IN` carries one :class:`Status` per
packet (:data:`STATUS_SIZE` bytes). All fields little-endian, fixed sizes, no padding.

Host → board frame (18 bytes)::

    off size field          type  meaning
    0   2    magic          u16   0x5642 (bytes 0x42 0x56, "BV")
    2   1    version        u8    1
    3   1    flags          u8    bit 0 ON, bit 1 AM (perceptual), bits 2-7 zero
    4   2    seq            u16   +1 per frame, wraps 65535 → 0
    6   2    ttl_ms         u16   1..1000: silence if no valid frame arrives within it
    8   4    frequency_mhz  u32   carrier frequency, milli-hertz, 0..20 000 000 (20 kHz)
    12  2    amplitude_q15  u16   0..32767 = 0..1 of full scale
    14  2    am_hz          u16   AM rate, Hz, 1..1000 when AM is set, else 0
    16  2    crc            u16   CRC-16/CCITT-FALSE of bytes 0..15

Board → host status (18 bytes)::

    off size field          type  meaning
    0   2    magic          u16   0x5342 (bytes 0x42 0x53, "BS")
    2   1    version        u8    1
    3   1    state          u8    bit 0 OUTPUT_ON, bit 1 TTL_EXPIRED, bit 2 AM_ACTIVE
    4   2    last_seq       u16   seq of the last *accepted* frame (0 before the first)
    6   2    faults         u16   FAULT_* bits, latched until this status has been sent
    8   4    underruns      u32   DAC/DMA underruns since power-up (wraps)
    12  2    rejected       u16   frames rejected since power-up (wraps)
    14  2    level_q15      u16   measured output level (peak over the last ≥ 10 ms), Q15
    16  2    crc            u16   CRC-16/CCITT-FALSE of bytes 0..15

Board behaviour (what firmware and emulators must do):

- A valid frame takes effect at once: the output ramps linearly to the new amplitude within
  :data:`RAMP_MAX_MS`, the oscillator keeps its phase across frequency changes. Output is
  silent when ON is clear, amplitude is 0 or frequency is 0. With AM set the carrier is
  multiplied by ``0.5 − 0.5·cos(2π·am_hz·t)``.
- TTL watchdog: if no *valid* frame arrives within ``ttl_ms`` of the last valid one, the
  board ramps to silence (within :data:`RAMP_MAX_MS`), sets STATE_TTL_EXPIRED and latches
  FAULT_TTL_EXPIRED; the next valid frame clears STATE_TTL_EXPIRED. Power-up state is silent.
- A bad frame (checked in order: length, magic, version, CRC, values) is discarded whole: the
  output does not change, it does **not** refresh the TTL, ``rejected`` counts it, and its
  FAULT_* bit is latched (:class:`ProtocolError` ``.fault`` names the bit).
- After every OUT packet (valid or not) the board queues one status on EP_IN, replacing any
  status still unread (the host reads the newest, non-blocking). Latched faults clear once a
  status carrying them has been sent.
- The host sends at most one frame per :data:`MIN_FRAME_INTERVAL_NS` and, while output is
  to continue, the next frame well before the last one's TTL runs out (burrforce's driver:
  on every change, else every ``watchdog / 2``). ``seq`` is echoed in ``last_seq`` and not otherwise
  checked (bulk transfers arrive in order).

Why frequency is a u32 in milli-hertz, not a float32: the board's DDS needs an integer phase
increment (``inc = f_mHz · 2³² / (1000 · rate)``), cheap-MCU cores (RP2040's Cortex-M0+) have
no FPU, an integer has no NaN/Inf to reject, and 1 mHz steps up to 4.29 MHz are far finer than
anyone feels. Amplitude is Q15 (u16, ≤ 32767) for the same reasons; 1/32767 of full scale
is below any voice coil's noise floor.

CRC-16/CCITT-FALSE: polynomial 0x1021, init 0xFFFF, refin false, refout false, xorout 0x0000;
check value ``crc16(b"123456789") == 0x29B1``.
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass

from ..usb_ids import BOARD_PID, BOARD_VID

# -- USB identity (the ids: devices.usb_ids) -----------------------------------------------
VID, PID = BOARD_VID, BOARD_PID
INTERFACE_CLASS = 0xFF
MANUFACTURER = "burrforce"
PRODUCT = "burrforce vibration board"
EP_OUT = 0x01
EP_IN = 0x81
MAX_PACKET_SIZE = 64  # full-speed bulk

PROTOCOL_VERSION = 1

# -- host → board frame ----------------------------------------------------------------------
FRAME_MAGIC = 0x5642  # b"BV" little-endian
FRAME_FORMAT = "<HBBHHIHH"  # everything before the CRC
FRAME_SIZE = struct.calcsize(FRAME_FORMAT) + 2  # 18

FLAG_ON = 0x01
FLAG_AM = 0x02
FLAGS_KNOWN = FLAG_ON | FLAG_AM

TTL_MIN_MS = 1
TTL_MAX_MS = 1000
TTL_DEFAULT_MS = 50
FREQUENCY_MAX_MHZ = 20_000_000  # 20 kHz: far above any voice coil, below 48 kHz Nyquist
AMPLITUDE_Q15_MAX = 32767
AM_HZ_MIN = 1
AM_HZ_MAX = 1000
AM_HZ_DEFAULT = 250
#: The host sends at most one frame per millisecond (1 kHz); the board accepts at least that.
MIN_FRAME_INTERVAL_NS = 1_000_000
#: On a new frame or on TTL expiry the board ramps amplitude linearly over at most this long.
RAMP_MAX_MS = 1

# -- board → host status ---------------------------------------------------------------------
STATUS_MAGIC = 0x5342  # b"BS" little-endian
STATUS_FORMAT = "<HBBHHIHH"
STATUS_SIZE = struct.calcsize(STATUS_FORMAT) + 2  # 18

STATE_OUTPUT_ON = 0x01
STATE_TTL_EXPIRED = 0x02
STATE_AM_ACTIVE = 0x04
STATES_KNOWN = STATE_OUTPUT_ON | STATE_TTL_EXPIRED | STATE_AM_ACTIVE

FAULT_BAD_LENGTH = 0x0001
FAULT_BAD_MAGIC = 0x0002
FAULT_BAD_VERSION = 0x0004
FAULT_BAD_CRC = 0x0008
FAULT_BAD_VALUE = 0x0010
FAULT_TTL_EXPIRED = 0x0020
FAULT_AMP_FAULT = 0x0040
FAULT_OVERTEMP = 0x0080
FAULT_UNDERRUN = 0x0100
FAULT_NAMES = {
    FAULT_BAD_LENGTH: "bad length", FAULT_BAD_MAGIC: "bad magic",
    FAULT_BAD_VERSION: "bad version", FAULT_BAD_CRC: "bad CRC", FAULT_BAD_VALUE: "bad value",
    FAULT_TTL_EXPIRED: "TTL expired", FAULT_AMP_FAULT: "amplifier fault",
    FAULT_OVERTEMP: "over-temperature", FAULT_UNDERRUN: "DAC underrun",
}

class ProtocolError(ValueError):
    """A frame or status the protocol rejects. ``fault`` is the FAULT_* bit a board sets for
    it (what an emulator or firmware reports back in :class:`Status`)."""

    def __init__(self, message: str, fault: int) -> None:
        super().__init__(message)
        self.fault = fault


CRC_CHECK_INPUT = b"123456789"
CRC_CHECK_VALUE = 0x29B1


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, xorout 0) of ``data``:
    the standard library's ``binascii.crc_hqx`` with that initial value."""
    return binascii.crc_hqx(data, crc)


@dataclass(frozen=True)
class Frame:
    """One host → board frame, in wire units.

    Attributes:
        seq: u16 sequence number.
        frequency_mhz: carrier frequency, milli-hertz.
        amplitude_q15: 0..32767 = 0..1 of the board's full-scale output.
        on: output enabled (off, or amplitude 0, means silence).
        am: perceptual amplitude modulation at ``am_hz`` (raised cosine, 0..1).
        ttl_ms: the board's watchdog: silent if no valid frame follows within it, ms.
        am_hz: AM rate, Hz (0 when ``am`` is off).
        version: protocol version (1).
    """

    seq: int
    frequency_mhz: int
    amplitude_q15: int
    on: bool
    am: bool = False
    ttl_ms: int = TTL_DEFAULT_MS
    am_hz: int = 0
    version: int = PROTOCOL_VERSION

    @property
    def frequency_hz(self) -> float:
        return self.frequency_mhz / 1000.0

    @property
    def amplitude(self) -> float:
        """Amplitude as a fraction 0..1 of full scale."""
        return self.amplitude_q15 / AMPLITUDE_Q15_MAX

    @property
    def flags(self) -> int:
        return (FLAG_ON if self.on else 0) | (FLAG_AM if self.am else 0)

    @property
    def audible(self) -> bool:
        """Whether this frame makes the board produce output."""
        return self.on and self.amplitude_q15 > 0 and self.frequency_mhz > 0


@dataclass(frozen=True)
class Status:
    """One board → host status, in wire units (see the module docstring's table)."""

    last_seq: int
    state: int = 0
    faults: int = 0
    underruns: int = 0
    rejected: int = 0
    level_q15: int = 0
    version: int = PROTOCOL_VERSION

    @property
    def output_on(self) -> bool:
        return bool(self.state & STATE_OUTPUT_ON)

    @property
    def ttl_expired(self) -> bool:
        return bool(self.state & STATE_TTL_EXPIRED)

    @property
    def level(self) -> float:
        """Measured output level as a fraction 0..1 of full scale."""
        return self.level_q15 / AMPLITUDE_Q15_MAX

    def fault_names(self) -> list[str]:
        """The names of the set fault bits (unknown bits as ``bit N``)."""
        names = []
        for bit in range(16):
            if self.faults & (1 << bit):
                names.append(FAULT_NAMES.get(1 << bit, f"bit {bit}"))
        return names


def frequency_to_mhz(frequency_hz: float) -> int:
    """Hz → the frame's u32 milli-hertz, rounded; ValueError outside 0..20 kHz or non-finite."""
    if not math.isfinite(frequency_hz) or frequency_hz < 0.0:
        raise ValueError(f"frequency must be finite and ≥ 0 Hz, got {frequency_hz}")
    mhz = round(frequency_hz * 1000.0)
    if mhz > FREQUENCY_MAX_MHZ:
        raise ValueError(f"frequency {frequency_hz} Hz above the board's "
                         f"{FREQUENCY_MAX_MHZ / 1000:.0f} Hz")
    return mhz


def amplitude_to_q15(amplitude: float) -> int:
    """Fraction 0..1 of full scale → Q15, rounded; ValueError outside [0, 1] or non-finite."""
    if not math.isfinite(amplitude) or not 0.0 <= amplitude <= 1.0:
        raise ValueError(f"amplitude must be in [0, 1] of full scale, got {amplitude}")
    return round(amplitude * AMPLITUDE_Q15_MAX)


def _check_frame_values(seq: int, frequency_mhz: int, amplitude_q15: int, flags: int,
                        ttl_ms: int, am_hz: int) -> None:
    if not 0 <= seq <= 0xFFFF:
        raise ValueError(f"seq must be a u16, got {seq}")
    if flags & ~FLAGS_KNOWN & 0xFF:
        raise ValueError(f"reserved flag bits set: 0x{flags:02x}")
    if not 0 <= frequency_mhz <= FREQUENCY_MAX_MHZ:
        raise ValueError(f"frequency_mhz must be 0..{FREQUENCY_MAX_MHZ}, got {frequency_mhz}")
    if not 0 <= amplitude_q15 <= AMPLITUDE_Q15_MAX:
        raise ValueError(f"amplitude_q15 must be 0..{AMPLITUDE_Q15_MAX}, got {amplitude_q15}")
    if not TTL_MIN_MS <= ttl_ms <= TTL_MAX_MS:
        raise ValueError(f"ttl_ms must be {TTL_MIN_MS}..{TTL_MAX_MS}, got {ttl_ms}")
    if flags & FLAG_AM:
        if not AM_HZ_MIN <= am_hz <= AM_HZ_MAX:
            raise ValueError(f"am_hz must be {AM_HZ_MIN}..{AM_HZ_MAX} with AM set, got {am_hz}")
    elif am_hz != 0:
        raise ValueError(f"am_hz must be 0 without the AM flag, got {am_hz}")


def encode_frame(seq: int, frequency_mhz: int, amplitude_q15: int, on: bool = True,
                 am: bool = False, ttl_ms: int = TTL_DEFAULT_MS, am_hz: int | None = None) -> bytes:
    """The 18-byte host → board frame. ``am_hz`` defaults to 250 with ``am``, else 0.
    ``seq`` is taken mod 2¹⁶. ValueError on any out-of-range field."""
    if am_hz is None:
        am_hz = AM_HZ_DEFAULT if am else 0
    seq &= 0xFFFF
    flags = (FLAG_ON if on else 0) | (FLAG_AM if am else 0)
    _check_frame_values(seq, int(frequency_mhz), int(amplitude_q15), flags, int(ttl_ms),
                        int(am_hz))
    body = struct.pack(FRAME_FORMAT, FRAME_MAGIC, PROTOCOL_VERSION, flags, seq, int(ttl_ms),
                       int(frequency_mhz), int(amplitude_q15), int(am_hz))
    return body + struct.pack("<H", crc16_ccitt_false(body))


def encode(frame: Frame) -> bytes:
    """A :class:`Frame`'s bytes (same checks as :func:`encode_frame`)."""
    return encode_frame(frame.seq, frame.frequency_mhz, frame.amplitude_q15, frame.on,
                        frame.am, frame.ttl_ms, frame.am_hz)


def _check_envelope(data: bytes, size: int, magic: int, what: str) -> tuple:
    data = bytes(data)
    if len(data) != size:
        raise ProtocolError(f"{what}: bad length {len(data)} bytes, expected {size}",
                            FAULT_BAD_LENGTH)
    fmt = FRAME_FORMAT if what == "frame" else STATUS_FORMAT
    fields = struct.unpack(fmt, data[:-2])
    if fields[0] != magic:
        raise ProtocolError(f"{what}: bad magic 0x{fields[0]:04x}, expected 0x{magic:04x}",
                            FAULT_BAD_MAGIC)
    if fields[1] != PROTOCOL_VERSION:
        raise ProtocolError(f"{what}: bad version {fields[1]}, expected {PROTOCOL_VERSION}",
                            FAULT_BAD_VERSION)
    (crc,) = struct.unpack("<H", data[-2:])
    expected = crc16_ccitt_false(data[:-2])
    if crc != expected:
        raise ProtocolError(f"{what}: bad CRC 0x{crc:04x}, computed 0x{expected:04x}",
                            FAULT_BAD_CRC)
    return fields


def decode_frame(data: bytes) -> Frame:
    """Parse a host → board frame. :class:`ProtocolError` (a ValueError; ``.fault`` the bit a
    board latches) naming what is wrong, checked in the order the board checks: length,
    magic, version, CRC, then field values (reserved flags, ranges)."""
    _, version, flags, seq, ttl_ms, frequency_mhz, amplitude_q15, am_hz = _check_envelope(
        data, FRAME_SIZE, FRAME_MAGIC, "frame")
    try:
        _check_frame_values(seq, frequency_mhz, amplitude_q15, flags, ttl_ms, am_hz)
    except ValueError as exc:
        raise ProtocolError(f"frame: bad value: {exc}", FAULT_BAD_VALUE) from None
    return Frame(seq=seq, frequency_mhz=frequency_mhz, amplitude_q15=amplitude_q15,
                 on=bool(flags & FLAG_ON), am=bool(flags & FLAG_AM), ttl_ms=ttl_ms,
                 am_hz=am_hz, version=version)


def encode_status(last_seq: int, state: int = 0, faults: int = 0, underruns: int = 0,
                  rejected: int = 0, level_q15: int = 0) -> bytes:
    """The 18-byte board → host status. Counters are taken mod their width (they wrap on the
    board); ValueError on other out-of-range fields."""
    if not 0 <= last_seq <= 0xFFFF:
        raise ValueError(f"last_seq must be a u16, got {last_seq}")
    if state & ~STATES_KNOWN & 0xFF or not 0 <= state <= 0xFF:
        raise ValueError(f"unknown state bits: 0x{state:x}")
    if not 0 <= faults <= 0xFFFF:
        raise ValueError(f"faults must be a u16, got {faults}")
    if not 0 <= level_q15 <= AMPLITUDE_Q15_MAX:
        raise ValueError(f"level_q15 must be 0..{AMPLITUDE_Q15_MAX}, got {level_q15}")
    body = struct.pack(STATUS_FORMAT, STATUS_MAGIC, PROTOCOL_VERSION, state, last_seq, faults,
                       underruns & 0xFFFFFFFF, rejected & 0xFFFF, level_q15)
    return body + struct.pack("<H", crc16_ccitt_false(body))


def decode_status(data: bytes) -> Status:
    """Parse a board → host status. ValueError naming what is wrong: length, magic, version,
    CRC, level out of range."""
    _, version, state, last_seq, faults, underruns, rejected, level_q15 = _check_envelope(
        data, STATUS_SIZE, STATUS_MAGIC, "status")
    if level_q15 > AMPLITUDE_Q15_MAX:
        raise ProtocolError(f"status: bad value: level_q15 {level_q15} > {AMPLITUDE_Q15_MAX}",
                            FAULT_BAD_VALUE)
    return Status(last_seq=last_seq, state=state, faults=faults, underruns=underruns,
                  rejected=rejected, level_q15=level_q15, version=version)
