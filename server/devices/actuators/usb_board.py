"""The burrforce vibration board over USB (pyusb + libusb): parameters out, status in.

The board synthesizes the waveform itself (``board_protocol``); this driver turns updates into
frames. :meth:`UsbBoardActuator.update` only drops the newest parameters into a one-slot
mailbox; a sender thread writes them to the bulk OUT endpoint (at most one frame per
millisecond, and only when something changed or half the TTL has passed) and reads the
board's status back without waiting for it. So a USB hiccup never stalls the device loop.

Watchdog: every frame's TTL is the time left until ``last update + watchdog_ms``, less the
board's 1 ms ramp and 1 ms for the frame's USB trip, so when the updates stop the board is
silent by then, on its own, whatever happens to the host, the thread or the cable.
"""

from __future__ import annotations

import errno
import threading
import time
from collections import deque
from typing import Any

from ..base import DeviceError, DeviceNotFound
from ..udev import backend_access_help
from ..usb import is_timeout, libusb_backend, usb_error
from . import board_protocol as bp
from .base import Actuator
from .synth import Perceptual

LABEL = "burrforce vibration board"


def map_usb_error(exc: BaseException, doing: str) -> DeviceError:
    """The DeviceError for a pyusb error raised while ``doing``."""
    return usb_error(exc, doing, LABEL, backend_access_help("usb"))


class UsbBoardActuator(Actuator):
    """Vibration through the burrforce vibration board (``board_protocol``).

    Args:
        serial: the board's USB serial number, when several are plugged in (None: the first).
        full_scale_N, watchdog_ms: see :class:`~.base.Actuator`; the watchdog becomes the
            frames' TTL (1..1000 ms).
        perceptual: ``"am"`` sets the frame's AM flag above the corner, ``"clamp"`` sends the
            corner frequency.
        max_rate_hz: most frames per second (≤ 1000, the protocol's limit).
        backend: a pyusb backend (default ``devices.usb.libusb_backend``).
        write_timeout_ms: how long the sender thread waits for one bulk OUT transfer.
    """

    def __init__(self, serial: str | None = None, *, full_scale_N: float = 1.0,
                 watchdog_ms: float = 50.0, perceptual: Perceptual | str | None = None,
                 max_rate_hz: float = 1000.0, backend: Any = None,
                 write_timeout_ms: int = 20) -> None:
        super().__init__(full_scale_N, watchdog_ms)
        if not 0.0 < max_rate_hz <= 1e9 / bp.MIN_FRAME_INTERVAL_NS:
            raise ValueError(f"max_rate_hz must be in (0, 1000], got {max_rate_hz}")
        if watchdog_ms < 10:
            raise ValueError(f"watchdog_ms must be ≥ 10 for the board, got {watchdog_ms}")
        self.serial = serial
        self.perceptual = Perceptual.of(perceptual)
        self.min_interval_ns = int(1e9 / max_rate_hz)
        self.write_timeout_ms = int(write_timeout_ms)
        self._backend = backend
        self._dev: Any = None
        self._interface = 0
        self._thread: threading.Thread | None = None
        self._wake = threading.Event()
        self._stop = False
        # one-slot mailbox (q15, mhz, am, update ns): append/popleft are atomic, the newest
        # replaces an unsent one
        self._pending: deque[tuple[int, int, bool, int]] = deque(maxlen=1)
        self._last_queued: tuple[int, int, bool] | None = None
        self._keepalive_due_ns = 0
        self._seq = 0
        self._error: DeviceError | None = None
        #: the newest status the board sent (None until one arrived)
        self.status: bp.Status | None = None
        #: every fault bit any status carried since open (the board latches them per status)
        self.faults_seen = 0
        self.frames_sent = 0
        self.last_frame: bytes | None = None

    # -- the caller's thread ------------------------------------------------------------------
    def _frame_params(self, level: float, frequency_hz: float) -> tuple[int, int, bool]:
        carrier_hz, depth = self.perceptual.carrier(frequency_hz)
        q15 = bp.amplitude_to_q15(level)
        if q15 == 0 or frequency_hz <= 0.0:
            return 0, 0, False
        return q15, bp.frequency_to_mhz(min(carrier_hz, bp.FREQUENCY_MAX_MHZ / 1000.0)), \
            depth > 0.0

    def _set(self, level: float, frequency_hz: float, t_ns: int, arrival_ns: int) -> None:
        if self._error is not None:
            raise self._error
        params = self._frame_params(level, frequency_hz)
        if params != self._last_queued or arrival_ns >= self._keepalive_due_ns:
            self._last_queued = params
            self._keepalive_due_ns = arrival_ns + self.watchdog_ns // 2
            self._pending.append((*params, arrival_ns))
            self._wake.set()

    # -- open / close -------------------------------------------------------------------------
    def _find(self) -> Any:
        import usb.core

        backend = self._backend or libusb_backend(LABEL)
        try:
            devices = list(usb.core.find(find_all=True, idVendor=bp.VID, idProduct=bp.PID,
                                         backend=backend))
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "listing USB devices") from exc
        if self.serial is not None:
            found = []
            for dev in devices:
                try:
                    if dev.serial_number == self.serial:
                        found.append(dev)
                except (usb.core.USBError, ValueError) as exc:
                    raise map_usb_error(exc, "reading a board's serial number") from exc
            devices = found
        if not devices:
            which = f" with serial {self.serial!r}" if self.serial else ""
            raise DeviceNotFound(f"no {LABEL} (USB {bp.VID:04x}:{bp.PID:04x}){which} found; "
                                 f"is it plugged in? (lsusb -d {bp.VID:04x}:{bp.PID:04x})")
        return devices[0]

    def _open(self) -> None:
        import usb.core
        import usb.util

        dev = self._find()
        self._dev = dev  # _close releases it whatever stops this open part-way
        try:
            try:
                dev.set_configuration()
            except usb.core.USBError as exc:
                if getattr(exc, "errno", None) != errno.EBUSY:
                    raise
            cfg = dev.get_active_configuration()
            intf = usb.util.find_descriptor(cfg, bInterfaceClass=bp.INTERFACE_CLASS)
            if intf is None:
                raise DeviceError(f"USB {bp.VID:04x}:{bp.PID:04x} has no vendor-class (0xFF) "
                                  f"interface: not a {LABEL}")
            addrs = {ep.bEndpointAddress for ep in intf}
            if not {bp.EP_OUT, bp.EP_IN} <= addrs:
                raise DeviceError(f"USB {bp.VID:04x}:{bp.PID:04x} lacks bulk endpoints 0x01 / "
                                  f"0x81 (has {sorted(hex(a) for a in addrs)}): not a {LABEL}")
            self._interface = intf.bInterfaceNumber
            usb.util.claim_interface(dev, intf.bInterfaceNumber)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "opening the board") from exc
        self._error = None
        self._stop = False
        self._pending.clear()
        self._last_queued = None
        self._keepalive_due_ns = 0
        self.status = None
        self.faults_seen = 0
        self.frames_sent = 0
        self._thread = threading.Thread(target=self._run, name="burrforce-board", daemon=True)
        self._thread.start()

    def _close(self) -> None:
        import usb.util

        self._stop = True
        self._wake.set()
        thread, self._thread = self._thread, None
        try:
            if thread is not None:
                thread.join(timeout=1.0)
        except RuntimeError:  # an open stopped before the thread started: nothing to join
            pass
        finally:
            dev, self._dev = self._dev, None
            if dev is not None:
                try:
                    usb.util.release_interface(dev, self._interface)
                except Exception:  # the board may be gone; nothing more to release then
                    pass
                usb.util.dispose_resources(dev)

    # -- the sender thread --------------------------------------------------------------------
    def _run(self) -> None:
        last_write_ns = 0
        while True:
            self._wake.wait(timeout=0.1)
            self._wake.clear()
            try:
                pending = self._pending.popleft()
            except IndexError:
                pending = None
            if self._stop:
                # Always end on an explicit "off" frame, whatever was pending.
                self._send_safely((0, 0, False, time.monotonic_ns()), last_write_ns)
                return
            if pending is None:
                continue
            last_write_ns = self._send_safely(pending, last_write_ns)
            if self._error is not None:
                return

    def _send_safely(self, pending: tuple[int, int, bool, int], last_write_ns: int) -> int:
        try:
            return self._send(pending, last_write_ns)
        except DeviceError as exc:
            self._error = exc
        except Exception as exc:  # a thread must not die silently
            self._error = DeviceError(f"{LABEL} sender failed: {exc!r}")
        return last_write_ns

    def _send(self, pending: tuple[int, int, bool, int], last_write_ns: int) -> int:
        import usb.core

        q15, mhz, am, update_ns = pending
        wait_ns = last_write_ns + self.min_interval_ns - time.monotonic_ns()
        if wait_ns > 0:
            time.sleep(wait_ns / 1e9)
        now = time.monotonic_ns()
        # The TTL runs to last update + watchdog, less the board's ramp and 1 ms for the
        # frame's trip over USB, so the board is silent by then.
        ttl_ms = (update_ns + self.watchdog_ns - now) // 1_000_000 - bp.RAMP_MAX_MS - 1
        on = q15 > 0
        if ttl_ms < bp.TTL_MIN_MS:  # already stale: the board must not sound
            on, q15, mhz, am, ttl_ms = False, 0, 0, False, bp.TTL_MIN_MS
        ttl_ms = min(int(ttl_ms), bp.TTL_MAX_MS)
        frame = bp.encode_frame(self._seq, mhz, q15, on=on, am=am, ttl_ms=ttl_ms,
                                am_hz=round(self.perceptual.am_hz) if am else 0)
        try:
            self._dev.write(bp.EP_OUT, frame, timeout=self.write_timeout_ms)
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "sending a frame") from exc
        self._seq = (self._seq + 1) & 0xFFFF
        self.frames_sent += 1
        self.stats.blocks += 1
        self.last_frame = frame
        self._read_status()
        return now

    def _read_status(self) -> None:
        import usb.core

        try:
            data = bytes(self._dev.read(bp.EP_IN, bp.MAX_PACKET_SIZE, timeout=1))
        except usb.core.USBError as exc:
            if is_timeout(exc):
                return  # no status yet: the next frame's read gets the newest
            raise map_usb_error(exc, "reading the status") from exc
        try:
            status = bp.decode_status(data)
        except ValueError as exc:
            raise DeviceError(f"the {LABEL} sent a bad status: {exc}") from exc
        self.status = status
        self.faults_seen |= status.faults
        self.stats.underruns = status.underruns
