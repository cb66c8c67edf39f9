"""The Novint Falcon's wire protocol: USB identity, FTDI set-up values, bootloader handshake and
the 16-byte I/O packets of the Novint SDK firmware.

Facts from libnifalcon (BSD-3, (c) 2007-2009 Nonpolynomial Labs/Kyle Machulis; see
``docs/devices.md``); this module restates them, it holds none of that project's code.

Packets, 16 bytes each way, one reply per command::

    host → device   '<'  m0 m0 m0 m0  m1 m1 m1 m1  m2 m2 m2 m2  flags  0  '>'
    device → host   '<'  e0 e0 e0 e0  e1 e1 e1 e1  e2 e2 e2 e2  status 0  '>'

Bytes 1..14 are each offset by +0x41. Motor commands and encoder counts are signed int16
split into four nibbles, least-significant nibble first. ``flags``: bit 0 homing mode, bits 1-3
the LEDs. ``status``: bits 0-3 the grip buttons, bits 4-6 the per-axis "homed" flags.

Both sides are here: the host encodes commands and decodes status; the device side (the
umockdev emulation) decodes commands and encodes status.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import TypeVar

from ..usb_ids import FALCON_PID, FALCON_VID

T = TypeVar("T")

# --- USB identity (the ids: devices.usb_ids) ----------------------------------------------
VID, PID = FALCON_VID, FALCON_PID

INTERFACE = 0
EP_OUT = 0x02
EP_IN = 0x81
#: Full-speed bulk packet size; every IN packet starts with FTDI_STATUS_BYTES modem status.
USB_PACKET_BYTES = 64
FTDI_STATUS_BYTES = 2
PACKET_BYTES = 16

# --- FTDI vendor control requests (bmRequestType FTDI_REQUEST_OUT, wIndex FTDI_INDEX) -------

FTDI_REQUEST_OUT = 0x40
#: wIndex of every FTDI request: the single-port chip takes 0 ("any interface").
FTDI_INDEX = 0
CONTROL_TIMEOUT_MS = 1000

SIO_RESET = 0
SIO_RESET_SIO = 0
SIO_RESET_PURGE_RX = 1
SIO_RESET_PURGE_TX = 2

SIO_MODEM_CTRL = 1
#: wValue of SIO_MODEM_CTRL: high byte = which lines to change, low byte = their new level.
MODEM_DTR_LOW = 0x0100
MODEM_DTR_HIGH = 0x0101
MODEM_RTS_LOW = 0x0200
MODEM_RTS_HIGH = 0x0202

SIO_SET_FLOW_CTRL = 2
FLOW_CONTROL_OFF = 0

SIO_SET_BAUD_RATE = 3
#: Baud divisors of the 3 MHz FTDI clock (bits 14-15 a fractional eighth code: 0x4000 = .5).
BAUD_DIVISOR_9600 = 0x4138          # 3 MHz / 312.5 = 9600 Bd: bootloader handshake
BAUD_DIVISOR_FIRMWARE = 0x15        # 3 MHz / 21 ≈ 142.9 kBd: firmware upload
BAUD_DIVISOR_NORMAL = 0x2           # 3 MHz / 2 = 1.5 MBd: I/O cycles

SIO_SET_DATA = 4
#: wValue of SIO_SET_DATA: 8 data bits, no parity (bits 8-10 = 0), one stop bit (bits 11-12).
LINE_8N1 = 0x0008

SIO_SET_LATENCY_TIMER = 9
LATENCY_FIRMWARE_MS = 16
LATENCY_NORMAL_MS = 1

# --- bootloader handshake and firmware upload --------------------------------------------

FIRMWARE_PROBE = b"\x0a\x43\x0d"
FIRMWARE_PROBE_REPLY = b"\x0a\x44\x2c\x0d"
#: Sent at BAUD_DIVISOR_FIRMWARE to start the upload; the bootloader echoes it.
FIRMWARE_UPLOAD_START = b"A"
FIRMWARE_HANDSHAKE_TRIES = 100
#: The image goes out in chunks this size; the bootloader echoes every byte.
FIRMWARE_CHUNK_BYTES = 62

# --- I/O packet fields ------------------------------------------------------------------

PACKET_START = 0x3C  # '<'
PACKET_END = 0x3E    # '>'
NIBBLE_OFFSET = 0x41

HOMING_BIT = 0x1
LED_GREEN = 0x2
LED_BLUE = 0x4
LED_RED = 0x8
LED_MASK = LED_GREEN | LED_BLUE | LED_RED

BUTTON_MASK = 0x0F
HOMED_SHIFT = 4
HOMED_MASK = 0x7

INT16_MIN = -32768
INT16_MAX = 32767

_FLAGS_BYTE = 13
_SPARE_BYTE = 14


def _check_int16_triple(values: Sequence[int], what: str) -> tuple[int, int, int]:
    if len(values) != 3:
        raise ValueError(f"{what} needs 3 values, got {len(values)}")
    out = []
    for i, v in enumerate(values):
        try:
            iv = int(v)
        except (TypeError, ValueError):
            raise ValueError(f"{what}[{i}] must be an integer, got {v!r}") from None
        if iv != v:
            raise ValueError(f"{what}[{i}] must be an integer, got {v!r}")
        if not INT16_MIN <= iv <= INT16_MAX:
            raise ValueError(f"{what}[{i}] = {iv} is outside int16 [{INT16_MIN}, {INT16_MAX}]")
        out.append(iv)
    return out[0], out[1], out[2]


def _encode(values: tuple[int, int, int], flags: int) -> bytes:
    packet = bytearray(PACKET_BYTES)
    packet[0] = PACKET_START
    packet[-1] = PACKET_END
    for axis, value in enumerate(values):
        word = value & 0xFFFF
        for k in range(4):
            packet[1 + 4 * axis + k] = ((word >> (4 * k)) & 0xF) + NIBBLE_OFFSET
    packet[_FLAGS_BYTE] = flags + NIBBLE_OFFSET
    packet[_SPARE_BYTE] = NIBBLE_OFFSET
    return bytes(packet)


def _decode(packet: bytes, what: str, flags_max: int) -> tuple[tuple[int, int, int], int]:
    if not isinstance(packet, (bytes, bytearray, memoryview)):
        raise ValueError(f"a Falcon {what} packet must be bytes, got {type(packet).__name__}")
    packet = bytes(packet)
    if len(packet) != PACKET_BYTES:
        raise ValueError(f"a Falcon {what} packet is {PACKET_BYTES} bytes, got {len(packet)}")
    if packet[0] != PACKET_START or packet[-1] != PACKET_END:
        raise ValueError(f"Falcon {what} packet not framed by '<' ... '>': {packet.hex(' ')}")
    values = []
    for axis in range(3):
        word = 0
        for k in range(4):
            b = packet[1 + 4 * axis + k]
            nib = b - NIBBLE_OFFSET
            if not 0 <= nib <= 0xF:
                raise ValueError(f"Falcon {what} packet byte {1 + 4 * axis + k} = {b:#04x} is "
                                 f"outside the nibble coding 0x41..0x50: {packet.hex(' ')}")
            word |= nib << (4 * k)
        values.append(word - 0x10000 if word & 0x8000 else word)
    flags = packet[_FLAGS_BYTE] - NIBBLE_OFFSET
    if not 0 <= flags <= flags_max:
        raise ValueError(f"Falcon {what} packet flags byte {packet[_FLAGS_BYTE]:#04x} is outside "
                         f"0x41..{flags_max + NIBBLE_OFFSET:#04x}: {packet.hex(' ')}")
    spare = packet[_SPARE_BYTE] - NIBBLE_OFFSET
    if not 0 <= spare <= 0xF:
        raise ValueError(f"Falcon {what} packet byte 14 = {packet[_SPARE_BYTE]:#04x} is outside "
                         f"the nibble coding 0x41..0x50: {packet.hex(' ')}")
    return (values[0], values[1], values[2]), flags


def encode_command(motor: Sequence[int], leds: int = 0, homing: bool = False) -> bytes:
    """The 16-byte host → device packet: motor commands (3 signed int16), LED bits
    (``LED_*``), homing mode. Raises ValueError on a value outside int16 or unknown LED bits."""
    motors = _check_int16_triple(motor, "motor command")
    leds = int(leds)
    if leds & ~LED_MASK:
        raise ValueError(f"LED bits {leds:#x} outside {LED_MASK:#x} (LED_GREEN|LED_BLUE|LED_RED)")
    return _encode(motors, leds | (HOMING_BIT if homing else 0))


def decode_command(packet: bytes) -> tuple[tuple[int, int, int], int, bool]:
    """(motor commands, LED bits, homing mode) of a host → device packet (the device's view).
    Raises ValueError on a malformed packet."""
    motors, flags = _decode(packet, "command", 0xF)
    return motors, flags & LED_MASK, bool(flags & HOMING_BIT)


def encode_status(encoders: Sequence[int], buttons: int = 0,
                  homed: Sequence[bool] = (False, False, False)) -> bytes:
    """The 16-byte device → host packet: encoder counts (3 signed int16), grip button bits
    (low nibble), per-axis homed flags. Raises ValueError on out-of-range values."""
    counts = _check_int16_triple(encoders, "encoder")
    buttons = int(buttons)
    if buttons & ~BUTTON_MASK:
        raise ValueError(f"button bits {buttons:#x} outside {BUTTON_MASK:#x}")
    if len(homed) != 3:
        raise ValueError(f"homed needs 3 flags, got {len(homed)}")
    homed_bits = sum(1 << i for i, h in enumerate(homed) if h)
    return _encode(counts, buttons | (homed_bits << HOMED_SHIFT))


def decode_status(packet: bytes) -> tuple[tuple[int, int, int], int, tuple[bool, bool, bool]]:
    """(encoder counts, grip button bits, per-axis homed flags) of a device → host packet.
    Raises ValueError on a malformed packet."""
    counts, status = _decode(packet, "status", BUTTON_MASK | (HOMED_MASK << HOMED_SHIFT))
    homed = (status >> HOMED_SHIFT) & HOMED_MASK
    return counts, status & BUTTON_MASK, (bool(homed & 1), bool(homed & 2), bool(homed & 4))


def strip_ftdi_status(raw: bytes, max_packet: int = USB_PACKET_BYTES) -> bytes:
    """The payload of a bulk-IN read: drop the FTDI_STATUS_BYTES modem-status bytes at the
    start of every ``max_packet``-byte USB packet (the read may span several packets)."""
    if max_packet <= FTDI_STATUS_BYTES:
        raise ValueError(f"max_packet must exceed {FTDI_STATUS_BYTES}, got {max_packet}")
    raw = bytes(raw)
    if len(raw) <= max_packet:
        return raw[FTDI_STATUS_BYTES:]
    return b"".join(raw[i + FTDI_STATUS_BYTES:i + max_packet]
                    for i in range(0, len(raw), max_packet))


def split_packets(buf: bytearray, decode: Callable[[bytes], T]) -> Iterator[T | None]:
    """Take every whole packet off the front of ``buf`` (a serial byte stream), resyncing on
    ``'<'``: yields ``decode(packet)`` for each one that decodes and None for each run of bytes
    skipped (garbage before a ``'<'``, or a packet ``decode`` refused). An incomplete packet
    stays in ``buf`` for the next read. Both sides use it: the driver on status packets, the
    emulated Falcon on commands."""
    while True:
        start = buf.find(b"<")
        if start < 0:
            if buf:
                yield None
            buf.clear()
            return
        if start:
            del buf[:start]
            yield None
        if len(buf) < PACKET_BYTES:
            return
        try:
            item = decode(bytes(buf[:PACKET_BYTES]))
        except ValueError:
            del buf[:1]
            yield None
            continue
        del buf[:PACKET_BYTES]
        yield item
