"""The Falcon's FTDI USB-serial bridge over pyusb: set-up by vendor control transfers, bulk
writes, and bulk reads with the FTDI modem-status bytes stripped.

Every pyusb error leaves this module as a :class:`~..base.DeviceError`: unplugged or reset
→ :class:`DeviceDisconnected`, no permission → :class:`DeviceAccessDenied` (with the udev
rule to add), anything else → :class:`DeviceError`.
"""

from __future__ import annotations

import errno
import time
from array import array

import usb.core
import usb.util

from ..base import DeviceError
from ..udev import backend_access_help
from ..usb import LIBUSB_NOT_FOUND, is_timeout, usb_error
from . import protocol as P

#: Bytes asked of one bulk-IN transfer: four full-speed packets (62 payload bytes each).
READ_CHUNK_BYTES = 4 * P.USB_PACKET_BYTES


def map_usb_error(exc: BaseException, doing: str) -> DeviceError:
    """The DeviceError for a pyusb error raised while ``doing`` (e.g. "reading the Falcon")."""
    return usb_error(exc, doing, "Novint Falcon", backend_access_help("falcon"),
                     gone_hint="check its USB cable and power",
                     busy_hint="(a Falcon driver, another burrforce) has it open")


class FtdiLink:
    """One opened Falcon: its FTDI chip's set-up and its two bulk endpoints.

    ``open`` claims the interface (detaching a kernel driver first); ``close`` releases it.
    Not thread-safe: one device loop owns it.
    """

    def __init__(self, dev: usb.core.Device) -> None:
        self.dev = dev
        self._claimed = False
        self._raw = array("B", bytes(READ_CHUNK_BYTES))

    # --- open / close ---------------------------------------------------------------

    def open(self) -> None:
        """Detach any kernel driver, select the configuration, claim the interface."""
        dev = self.dev
        try:
            if dev.is_kernel_driver_active(P.INTERFACE):
                dev.detach_kernel_driver(P.INTERFACE)
        except NotImplementedError:
            pass  # not every backend/OS has kernel drivers to detach
        except usb.core.USBError as exc:
            # A missing driver (ENOENT/ENODATA) just means there is nothing to detach.
            if exc.errno not in (errno.ENOENT, errno.ENODATA, None) \
                    and exc.backend_error_code != LIBUSB_NOT_FOUND:
                raise map_usb_error(exc, "detaching the kernel driver") from exc
        try:
            try:
                dev.get_active_configuration()
            except usb.core.USBError:
                dev.set_configuration()
            usb.util.claim_interface(dev, P.INTERFACE)
            self._claimed = True
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "claiming the Falcon's USB interface") from exc

    def close(self) -> None:
        """Release the interface and the handle (best effort: never raises)."""
        try:
            if self._claimed:
                usb.util.release_interface(self.dev, P.INTERFACE)
        except (usb.core.USBError, ValueError):
            pass
        finally:
            self._claimed = False
            try:
                usb.util.dispose_resources(self.dev)
            except usb.core.USBError:  # pragma: no cover - already gone
                pass

    # --- FTDI set-up ------------------------------------------------------------------

    def control(self, request: int, value: int, what: str) -> None:
        """One FTDI vendor request (host→device, no data stage)."""
        try:
            self.dev.ctrl_transfer(P.FTDI_REQUEST_OUT, request, value, P.FTDI_INDEX, None,
                                   P.CONTROL_TIMEOUT_MS)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, f"setting the Falcon's {what}") from exc

    def purge(self) -> None:
        """Drop whatever the FTDI chip holds in both directions."""
        self.control(P.SIO_RESET, P.SIO_RESET_PURGE_RX, "RX purge")
        self.control(P.SIO_RESET, P.SIO_RESET_PURGE_TX, "TX purge")

    def set_latency_ms(self, ms: int) -> None:
        if not 1 <= ms <= 255:
            raise ValueError(f"FTDI latency timer must be 1..255 ms, got {ms}")
        self.control(P.SIO_SET_LATENCY_TIMER, ms, "latency timer")

    def set_baud_divisor(self, divisor: int) -> None:
        self.control(P.SIO_SET_BAUD_RATE, divisor, "baud rate")

    def set_line_8n1(self) -> None:
        self.control(P.SIO_SET_DATA, P.LINE_8N1, "line format")

    def set_flow_control_off(self) -> None:
        self.control(P.SIO_SET_FLOW_CTRL, P.FLOW_CONTROL_OFF, "flow control")

    def set_dtr(self, high: bool) -> None:
        self.control(P.SIO_MODEM_CTRL, P.MODEM_DTR_HIGH if high else P.MODEM_DTR_LOW, "DTR")

    def set_rts(self, high: bool) -> None:
        self.control(P.SIO_MODEM_CTRL, P.MODEM_RTS_HIGH if high else P.MODEM_RTS_LOW, "RTS")

    def bootloader_mode(self) -> None:
        """Serial settings of the bootloader handshake: 9600 Bd 8N1, no flow control, 16 ms
        latency, RTS low, DTR pulsed low → high (which resets the Falcon's controller)."""
        self.purge()
        self.set_latency_ms(P.LATENCY_FIRMWARE_MS)
        self.set_baud_divisor(P.BAUD_DIVISOR_9600)
        self.set_line_8n1()
        self.set_flow_control_off()
        self.set_rts(False)
        self.set_dtr(False)
        self.set_dtr(True)

    def normal_mode(self) -> None:
        """Serial settings of the I/O cycles: 1 ms latency, 1.5 MBd, buffers purged."""
        self.set_latency_ms(P.LATENCY_NORMAL_MS)
        self.set_baud_divisor(P.BAUD_DIVISOR_NORMAL)
        self.purge()

    # --- bulk I/O -----------------------------------------------------------------------

    def write(self, data: bytes, timeout_ms: int = 100) -> None:
        """Send ``data`` to the Falcon (raises DeviceError if not all of it went out)."""
        try:
            sent = self.dev.write(P.EP_OUT, data, timeout_ms)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "writing to the Falcon") from exc
        if sent != len(data):
            raise DeviceError(f"the Falcon took {sent} of {len(data)} bytes")

    def read_payload(self, timeout_ms: int) -> bytes:
        """One bulk-IN transfer's payload (FTDI status bytes stripped); b"" on a timeout."""
        try:
            n = self.dev.read(P.EP_IN, self._raw, max(1, int(timeout_ms)))
        except usb.core.USBError as exc:
            if is_timeout(exc):
                return b""
            raise map_usb_error(exc, "reading from the Falcon") from exc
        if n <= P.FTDI_STATUS_BYTES:
            return b""
        return P.strip_ftdi_status(self._raw[:n].tobytes())

    def bulk_read(self, n: int, timeout_s: float = 1.0) -> bytes:
        """Up to ``n`` payload bytes: reads until ``n`` have arrived or ``timeout_s`` passed
        (then returns what did arrive, possibly fewer or none). Bytes beyond ``n`` that came
        in the same transfer are returned too: the caller asked for at least ``n``."""
        if n < 0:
            raise ValueError(f"cannot read {n} bytes")
        deadline = time.monotonic() + timeout_s
        got = bytearray()
        while len(got) < n:
            left_ms = (deadline - time.monotonic()) * 1000.0
            if left_ms <= 0:
                break
            got += self.read_payload(min(left_ms, 1000.0))
        return bytes(got)
