"""What an emulated USB device *is*: its descriptors and what it does with each transfer.

An :class:`EmulatedFunction` runs inside the emulator process (``usbfs``); the host's driver
talks to it through real libusb and usbfs ioctls. A subclass sets the descriptor fields
(class attributes or in ``__init__``) and overrides the three transfer hooks:

- :meth:`EmulatedFunction.control` — a control transfer on endpoint 0 (standard requests are
  answered here; subclasses answer their vendor/class requests and defer to ``super()``);
- :meth:`EmulatedFunction.out` — data the host sent on an OUT endpoint;
- :meth:`EmulatedFunction.in_` — what the device answers on an IN endpoint, or None while it
  has nothing (the host's URB stays pending, as a real device NAKs).

A hook raises :class:`Stall` to answer STALL (the host sees EPIPE). Hooks run with the
emulator's lock held, one at a time; a function whose IN data appears later than the host's
request (a timer, a control-channel command) calls :meth:`EmulatedFunction.wake` so the
emulator retries pending IN requests at once.

Descriptor layouts and request codes are the USB 2.0 specification's (chapter 9).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

# bmRequestType parts and standard bRequest codes (USB 2.0 §9.3, §9.4).
DIR_IN = 0x80
TYPE_MASK = 0x60
TYPE_STANDARD = 0x00
TYPE_VENDOR = 0x40
RECIPIENT_MASK = 0x1F
RECIPIENT_DEVICE = 0
RECIPIENT_INTERFACE = 1
RECIPIENT_ENDPOINT = 2

GET_STATUS = 0
CLEAR_FEATURE = 1
SET_FEATURE = 3
GET_DESCRIPTOR = 6
GET_CONFIGURATION = 8
SET_CONFIGURATION = 9
GET_INTERFACE = 10
SET_INTERFACE = 11
FEATURE_ENDPOINT_HALT = 0

DESC_DEVICE = 1
DESC_CONFIGURATION = 2
DESC_STRING = 3
DESC_INTERFACE = 4
DESC_ENDPOINT = 5
LANGID_EN_US = 0x0409

TRANSFER_TYPES = {"bulk": 2, "interrupt": 3}
SPEEDS_MBPS = (1.5, 12, 480)


class Stall(Exception):
    """Raised by a hook: the endpoint answers STALL (the host's transfer fails with EPIPE)."""


@dataclass(frozen=True)
class Endpoint:
    """One endpoint of interface 0.

    Attributes:
        address: bEndpointAddress (bit 7 set = IN), 0x01..0x0F / 0x81..0x8F.
        transfer: ``bulk`` or ``interrupt``.
        max_packet: wMaxPacketSize, bytes (≤ 64 at full speed).
        interval: bInterval (interrupt: polling interval in frames, 1..255; bulk: 0).
    """

    address: int
    transfer: str = "bulk"
    max_packet: int = 64
    interval: int = 0

    def __post_init__(self) -> None:
        if not 1 <= self.address & 0x7F <= 15 or self.address & 0x70:
            raise ValueError(f"endpoint address {self.address:#04x} outside 0x01..0x0F/0x81..0x8F")
        if self.transfer not in TRANSFER_TYPES:
            raise ValueError(f"endpoint transfer must be one of {sorted(TRANSFER_TYPES)}, "
                             f"got {self.transfer!r}")
        if not 1 <= self.max_packet <= 1024:
            raise ValueError(f"max_packet must be 1..1024 bytes, got {self.max_packet}")
        if self.transfer == "interrupt" and not 1 <= self.interval <= 255:
            raise ValueError(f"an interrupt endpoint needs interval 1..255, got {self.interval}")

    def descriptor(self) -> bytes:
        return struct.pack("<BBBBHB", 7, DESC_ENDPOINT, self.address,
                           TRANSFER_TYPES[self.transfer], self.max_packet, self.interval)


class EmulatedFunction:
    """An emulated USB device with one configuration and one interface (number 0).

    Descriptor fields (override as class attributes or set in ``__init__``): ``vendor_id``,
    ``product_id``, ``bcd_device``, ``bcd_usb``, ``max_packet_ep0`` (8/16/32/64),
    ``manufacturer``/``product``/``serial`` (None = no string), ``interface_class``/
    ``_subclass``/``_protocol``, ``endpoints`` (tuple of :class:`Endpoint`), ``max_power_mA``,
    ``speed_mbps`` (1.5, 12 or 480).
    """

    vendor_id: int = 0x1209
    product_id: int = 0x0001
    bcd_device: int = 0x0100
    bcd_usb: int = 0x0200
    max_packet_ep0: int = 64
    manufacturer: str | None = None
    product: str | None = None
    serial: str | None = None
    interface_class: int = 0xFF
    interface_subclass: int = 0xFF
    interface_protocol: int = 0xFF
    endpoints: tuple[Endpoint, ...] = ()
    max_power_mA: int = 100
    speed_mbps: float = 12

    #: Set by the emulator: wakes it to retry pending IN requests (see :meth:`wake`).
    _waker: Callable[[], None] | None = None

    # -- descriptors -------------------------------------------------------------------

    def validate(self) -> None:
        """ValueError naming the first descriptor field out of range."""
        for name in ("vendor_id", "product_id", "bcd_device", "bcd_usb"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 0 <= value <= 0xFFFF:
                raise ValueError(f"{name} must be a u16, got {value!r}")
        if self.max_packet_ep0 not in (8, 16, 32, 64):
            raise ValueError(f"max_packet_ep0 must be 8, 16, 32 or 64, got {self.max_packet_ep0}")
        for name in ("interface_class", "interface_subclass", "interface_protocol"):
            if not 0 <= getattr(self, name) <= 0xFF:
                raise ValueError(f"{name} must be a u8, got {getattr(self, name)!r}")
        if self.speed_mbps not in SPEEDS_MBPS:
            raise ValueError(f"speed_mbps must be one of {SPEEDS_MBPS}, got {self.speed_mbps}")
        if not 0 <= self.max_power_mA <= 500:
            raise ValueError(f"max_power_mA must be 0..500, got {self.max_power_mA}")
        addresses = [ep.address for ep in self.endpoints]
        if len(set(addresses)) != len(addresses):
            raise ValueError(f"duplicate endpoint addresses {addresses}")
        for text in self.strings():
            if len(text) > 126:
                raise ValueError(f"string descriptor too long (> 126 characters): {text!r}")

    def strings(self) -> list[str]:
        """The string table, index 1 upwards (manufacturer, product, serial; those set)."""
        return [s for s in (self.manufacturer, self.product, self.serial) if s is not None]

    def _string_index(self, text: str | None) -> int:
        return 0 if text is None else self.strings().index(text) + 1

    def device_descriptor(self) -> bytes:
        """The 18-byte device descriptor."""
        return struct.pack("<BBHBBBBHHHBBBB", 18, DESC_DEVICE, self.bcd_usb, 0, 0, 0,
                           self.max_packet_ep0, self.vendor_id, self.product_id,
                           self.bcd_device, self._string_index(self.manufacturer),
                           self._string_index(self.product), self._string_index(self.serial), 1)

    def configuration_descriptor(self) -> bytes:
        """Configuration 1 with its interface and endpoint descriptors (wTotalLength bytes)."""
        interface = struct.pack("<BBBBBBBBB", 9, DESC_INTERFACE, 0, 0, len(self.endpoints),
                                self.interface_class, self.interface_subclass,
                                self.interface_protocol, 0)
        body = interface + b"".join(ep.descriptor() for ep in self.endpoints)
        header = struct.pack("<BBHBBBBB", 9, DESC_CONFIGURATION, 9 + len(body), 1, 1, 0, 0x80,
                             (self.max_power_mA + 1) // 2)
        return header + body

    def descriptors(self) -> bytes:
        """What Linux exposes as the sysfs ``descriptors`` attribute: device + configuration."""
        return self.device_descriptor() + self.configuration_descriptor()

    def string_descriptor(self, index: int, langid: int) -> bytes | None:
        """String descriptor ``index`` (0 = the language list); None if there is none."""
        if index == 0:
            return struct.pack("<BBH", 4, DESC_STRING, LANGID_EN_US)
        table = self.strings()
        if not 1 <= index <= len(table):
            return None
        text = table[index - 1].encode("utf-16-le")
        return bytes((2 + len(text), DESC_STRING)) + text

    def endpoint(self, address: int) -> Endpoint | None:
        for ep in self.endpoints:
            if ep.address == address:
                return ep
        return None

    # -- transfer hooks (run with the emulator's lock held) ------------------------------

    def control(self, request_type: int, request: int, value: int, index: int,
                data_or_length: bytes | int) -> bytes | int | None:
        """A control transfer. For a device-to-host request (``request_type & 0x80``)
        ``data_or_length`` is wLength and the answer is the bytes to return (at most wLength;
        the emulator truncates); for host-to-device it is the data stage (bytes) and any
        non-None answer acknowledges it. None (or raising :class:`Stall`) = STALL.

        The base class answers the standard requests; override for vendor/class requests
        and return ``super().control(...)`` for the rest."""
        if request_type & TYPE_MASK != TYPE_STANDARD:
            return None
        recipient = request_type & RECIPIENT_MASK
        if request_type & DIR_IN:
            if request == GET_DESCRIPTOR and recipient == RECIPIENT_DEVICE:
                kind, number = value >> 8, value & 0xFF
                if kind == DESC_DEVICE:
                    return self.device_descriptor()
                if kind == DESC_CONFIGURATION and number == 0:
                    return self.configuration_descriptor()
                if kind == DESC_STRING:
                    return self.string_descriptor(number, index)
                return None
            if request == GET_STATUS:
                return b"\x00\x00"
            if request == GET_CONFIGURATION:
                return b"\x01"
            if request == GET_INTERFACE and recipient == RECIPIENT_INTERFACE and index == 0:
                return b"\x00"
            return None
        if request in (CLEAR_FEATURE, SET_FEATURE) and recipient == RECIPIENT_ENDPOINT \
                and value == FEATURE_ENDPOINT_HALT:
            if request == CLEAR_FEATURE:
                self.clear_halt(index & 0xFF)
            return 0
        if request == SET_CONFIGURATION and value in (0, 1):
            return 0
        if request == SET_INTERFACE and recipient == RECIPIENT_INTERFACE and index == 0 \
                and value == 0:
            return 0
        return None

    def out(self, endpoint: int, data: bytes) -> None:
        """The host sent ``data`` on OUT ``endpoint``. Default: STALL."""
        raise Stall(f"endpoint {endpoint:#04x} takes no data")

    def in_(self, endpoint: int, max_len: int) -> bytes | None:
        """What IN ``endpoint`` answers now (at most ``max_len`` bytes; b"" is a zero-length
        packet), or None while there is nothing (the request stays pending). Called again
        whenever the emulator polls: on every host reap and after :meth:`wake`."""
        return None

    def clear_halt(self, endpoint: int) -> None:
        """The host cleared a halt on ``endpoint`` (CLEAR_HALT ioctl or CLEAR_FEATURE)."""

    def bus_reset(self) -> None:
        """The host reset the device (USBDEVFS_RESET)."""

    def power_off(self) -> None:
        """The device was unplugged: it lost power (motors, outputs stop)."""

    def power_cycle(self) -> None:
        """The device is plugged back in after an unplug: return to power-on state."""

    # -- emulator plumbing -------------------------------------------------------------

    def wake(self) -> None:
        """Tell the emulator new IN data may be there (thread-safe, never blocks)."""
        if self._waker is not None:
            self._waker()

    def commands(self) -> dict[str, Callable[..., Any]]:
        """Control-channel commands this function offers: name → callable taking keyword
        arguments (JSON values) and returning a JSON-able result. Run with the emulator's
        lock held."""
        return {}
