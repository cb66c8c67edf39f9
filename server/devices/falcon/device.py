"""The Novint Falcon as a :class:`~..base.HapticDevice`, over pyusb without the vendor SDK.

One :meth:`FalconDevice.cycle` is one write of a 16-byte command and one read of the 16-byte
status the firmware answers with, plus two numba kernels (force → motor commands at the last
position; encoders → position by forward kinematics seeded with the last position).

Frame: the device frame is the Falcon's own (libnifalcon's) frame with the origin moved to
:data:`~.kinematics.WORKSPACE_CENTRE_M` and lengths in mm: z points from the Falcon's body
towards the user, y up, x to the user's right. Forces are N along the same axes.

Safety: no force is sent until all three axes are homed (before homing the encoder counts
are relative, and forces computed from them push in arbitrary directions), and every
command keeps the homing bit set so the firmware keeps its reference.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import usb.core
from numba import njit

from ...haptics.profiles import PROFILES
from ...haptics.velocity import DeviceVelocity
from ..base import (
    DeviceError,
    DeviceInfo,
    DeviceNotFound,
    DeviceState,
    HapticDevice,
    clamp_force,
)
from ..usb import libusb_backend
from . import protocol as P
from .firmware import ensure_firmware, read_firmware_image
from .ftdi import FtdiLink, map_usb_error
from .kinematics import (
    WORKSPACE_CENTRE_M,
    WORKSPACE_RADIUS_M,
    encoder_to_angle,
    forward_kinematics,
    motor_torques,
    torques_to_commands,
)

log = logging.getLogger(__name__)

#: The Falcon's axes (x right, y up, z toward the user) → the common device frame (x toward
#: the user, y right, z up).
AXES = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))

#: How long one I/O cycle waits for the Falcon's reply (ms). It normally comes within 1–2 ms
#: (the FTDI latency timer is 1 ms); far longer means the device hangs.
REPLY_TIMEOUT_MS = 50
#: The velocity estimator's window (s): FOAW over the encoder-quantized positions.
VELOCITY_MAX_SPAN_S = 0.03
#: How often :meth:`FalconDevice.home` repeats its instructions (s).
HOMING_REMINDER_S = 5.0

_M_TO_MM = 1000.0


def default_backend():
    """A libusb-1.0 pyusb backend (``devices.usb.libusb_backend``)."""
    return libusb_backend("Falcon back-end")


@njit(cache=True, nogil=True)
def _commands_for_force(p_m: np.ndarray, force_N: np.ndarray) -> np.ndarray:
    """int16 motor commands ((3,) int64) for ``force_N`` (N, Falcon frame) at ``p_m`` (m)."""
    return torques_to_commands(motor_torques(p_m, force_N))


@njit(cache=True, nogil=True)
def _sense(enc: np.ndarray, p_m: np.ndarray) -> bool:
    """Forward kinematics of encoder counts ``enc`` ((3,) float) seeded by ``p_m`` (m, (3,));
    on convergence ``p_m`` takes the new position, else it keeps the last good one."""
    p, ok = forward_kinematics(encoder_to_angle(enc), p_m)
    if ok:
        p_m[:] = p
    return ok


class FalconDevice(HapticDevice):
    """A Novint Falcon on USB.

    Args:
        index: which Falcon, when several are plugged in (ordered by USB bus and address).
        firmware: path of the firmware image to upload when the Falcon runs none (it forgets
            it at power-off); e.g. libnifalcon's ``nvent_firmware.bin``. burrforce ships none.
        backend: a pyusb backend (default: :func:`default_backend`).

    After :meth:`open`, :meth:`home` (the user moves the grip through its range), then
    :meth:`cycle` at ~1 kHz. Counters: :attr:`fk_failures` (homed cycles whose position did
    not converge: the last good one was reported), :attr:`bad_packets` (malformed replies
    skipped), :attr:`cycles`.
    """

    def __init__(self, index: int = 0, firmware: str | None = None, backend=None) -> None:
        super().__init__()
        if isinstance(index, bool) or not isinstance(index, int) or index < 0:
            raise ValueError(f"Falcon index must be an integer >= 0, got {index!r}")
        if firmware is not None:
            read_firmware_image(firmware)  # refuse a file that is no image before any USB
        self.index = index
        self.firmware = firmware
        self._backend = backend
        self.info = DeviceInfo(backend="falcon", model="Novint Falcon",
                               limits=PROFILES["falcon"],
                               workspace_radius_mm=WORKSPACE_RADIUS_M * _M_TO_MM,
                               servo_rate_hz=1000.0, buttons=4, sensed_rotation=False,
                               axes=AXES)
        self._link: FtdiLink | None = None
        self._rx = bytearray()
        self._p_m = WORKSPACE_CENTRE_M.copy()
        self._force = np.zeros(3)
        self._enc = np.zeros(3)
        self._velocity = DeviceVelocity(self.info.limits.resolution_mm, VELOCITY_MAX_SPAN_S)
        self._homed = False
        self.fk_failures = 0
        self.bad_packets = 0
        self.cycles = 0
        self.firmware_status = ""

    # --- open / close ----------------------------------------------------------------

    def _open(self) -> None:
        backend = self._backend if self._backend is not None else default_backend()
        try:
            found = list(usb.core.find(find_all=True, idVendor=P.VID, idProduct=P.PID,
                                       backend=backend))
        except usb.core.USBError as exc:
            raise map_usb_error(exc, "listing USB devices") from exc
        found.sort(key=lambda d: (d.bus or 0, d.address or 0))
        if self.index >= len(found):
            raise DeviceNotFound(
                f"no Novint Falcon #{self.index} on USB ({len(found)} found, "
                f"id {P.VID:04x}:{P.PID:04x}); check that it is plugged in and powered "
                "(its power supply, not just USB)")
        dev = found[self.index]
        link = FtdiLink(dev)
        try:
            link.open()
            self.firmware_status = ensure_firmware(link, self.firmware, log.info)  # → normal mode
            log.info("Novint Falcon #%d (bus %s address %s): %s", self.index, dev.bus,
                     dev.address, self.firmware_status)
            self.info = replace(self.info, serial=f"usb:{dev.bus}-{dev.address}")
        except BaseException:
            # Not through _close: a Falcon whose firmware is not running gets no command.
            link.close()
            raise
        self._link = link  # from here on, _close zeroes and releases it
        self._reset_state()

    def _close(self) -> None:
        link, self._link = self._link, None
        if link is None:
            return
        try:
            link.write(P.encode_command((0, 0, 0), leds=0, homing=True))
        except DeviceError:
            pass  # the device may be gone: there is nothing left to zero
        link.close()

    def _reset_state(self) -> None:
        self._rx.clear()
        self._p_m[:] = WORKSPACE_CENTRE_M
        self._velocity.reset()
        self._homed = False

    # --- I/O ------------------------------------------------------------------------

    @property
    def homed(self) -> bool:
        """Whether the firmware reported all three axes homed in the last reply."""
        return self._homed

    def _exchange(self, command: bytes) -> tuple[tuple[int, int, int], int,
                                                 tuple[bool, bool, bool]]:
        """Send one command, return the newest well-formed status that came back."""
        link = self._link
        if link is None:
            raise DeviceError("the Falcon is not open")
        link.write(command)
        rx = self._rx
        newest = None
        deadline = time.monotonic() + REPLY_TIMEOUT_MS / 1000.0
        while True:
            for status in P.split_packets(rx, P.decode_status):
                if status is None:
                    self.bad_packets += 1
                else:
                    newest = status
            if newest is not None:
                return newest
            left_ms = (deadline - time.monotonic()) * 1000.0
            if left_ms <= 0:
                raise DeviceError(f"the Falcon did not answer an I/O packet within "
                                  f"{REPLY_TIMEOUT_MS} ms")
            rx += link.read_payload(left_ms)

    def cycle(self, force_N: np.ndarray) -> DeviceState:
        """One I/O cycle: send ``force_N`` ((3,), N, device frame; clamped to the profile's
        max force, zero until homed) and return the state it read back."""
        f = np.asarray(force_N, dtype=float)
        if f.shape != (3,):
            raise ValueError(f"force_N must have shape (3,), got {f.shape}")
        f, _ = clamp_force(f, self.info.limits.max_force_N)
        if self._homed:
            self._force[:] = f
            commands = _commands_for_force(self._p_m, self._force)
            leds = P.LED_GREEN
        else:
            commands = (0, 0, 0)
            leds = P.LED_RED
        command = P.encode_command((int(commands[0]), int(commands[1]), int(commands[2])),
                                   leds=leds, homing=True)
        # The firmware reads its encoders when the command arrives, a fraction of a ms after
        # the write; the reply then waits for the FTDI latency timer, and a host stall before
        # it is read (preemption, a collection) can add many ms more. Stamped after the read,
        # that delay lands on one sample's time and FOAW reads it as a jump in speed.
        t_ns = time.monotonic_ns()
        counts, buttons, homed = self._exchange(command)
        self.cycles += 1
        now_homed = homed[0] and homed[1] and homed[2]
        if now_homed != self._homed:
            # Homing redefines the encoders' zero: the old position and velocity are void.
            self._reset_state()
            self._homed = now_homed
        self._enc[0], self._enc[1], self._enc[2] = counts
        if not _sense(self._enc, self._p_m) and self._homed:
            self.fk_failures += 1
        x_mm = (self._p_m - WORKSPACE_CENTRE_M) * _M_TO_MM
        velocity = self._velocity.update(x_mm, t_ns * 1e-9)
        return DeviceState(position_mm=x_mm, velocity_mm_s=velocity.copy(),
                           buttons=buttons, t_ns=t_ns)

    def home(self, timeout_s: float = 30.0,
             progress: Callable[[str], None] | None = None,
             cancelled: Callable[[], bool] | None = None) -> bool:
        """Wait (cycling at zero force, red LED) until the firmware reports all three axes
        homed; then the LED turns green. The user must pull the grip all the way out and
        push it all the way in. True once homed; False if ``timeout_s`` passed first or
        ``cancelled()`` became true (asked once a cycle)."""
        if not self.is_open:
            raise DeviceError("open the Falcon before homing it")
        say = progress if progress is not None else log.info
        zero = np.zeros(3)
        self.cycle(zero)
        if self._homed:
            self.cycle(zero)  # the reply that says "homed" came to a red-light command
            return True
        instructions = ("Falcon: homing. Pull the grip all the way out towards you, then push "
                        "it all the way in; repeat until the light turns green.")
        say(instructions)
        deadline = time.monotonic() + timeout_s
        next_reminder = time.monotonic() + HOMING_REMINDER_S
        while time.monotonic() < deadline:
            if cancelled is not None and cancelled():
                return False
            self.cycle(zero)
            if self._homed:
                self.cycle(zero)
                say("Falcon: homed.")
                return True
            if time.monotonic() >= next_reminder:
                say(instructions)
                next_reminder += HOMING_REMINDER_S
        say(f"Falcon: not homed after {timeout_s:g} s.")
        return False
