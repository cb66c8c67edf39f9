"""Haply Inverse3 (and optionally its VerseGrip handle) through ``HaplyHardwareAPI``.

Install: ``pip install 'burrforce[haply]'`` (Haply's pybind11 wheel, which talks to the
device's USB serial port itself; no other SDK). On Linux the serial port (``/dev/ttyACM*``)
needs a udev rule or membership of the ``dialout`` group (``devices.udev``).

One :meth:`HaplyInverse3Device.cycle` is one ``Inverse3.end_effector_force(force)``
exchange: the device takes the force and answers its end-effector position and velocity.
Ports: the first of ``HaplyHardwareAPI.detect_inverse3s()`` unless ``port`` is given; the
device is woken with ``device_wakeup_dict()`` on open. The API does not raise when the device
stays silent (checked with HaplyHardwareAPI 0.1.13 on a pseudo-terminal): it logs to stderr
and returns made-up wake-up fields (an all-zero UUID) or an all-zero state after twice its
read timeout. This back-end treats those as no device (DeviceNotFound on open,
DeviceDisconnected in ``cycle``).

Frame: the Inverse3's base frame as the API reports it (right-handed: x to the operator's
right, y away from the operator, z up — per CHAI3D's Haply port, which maps it onto CHAI3D's
x-toward-operator frame), in mm and mm/s, moved so the origin is ``workspace_centre_m`` (default
(0.0186, −0.153, 0.151) m, the workspace centre in Haply's own position-control sample; it
depends on the arm's left/right-handed set-up: measure and pass yours). Forces in N, same axes.

VerseGrip: with ``handle_port`` (a port, or ``"auto"`` for the first of ``detect_handles()``)
a background thread polls ``Handle.GetVersegripStatus()`` (the handle is slower than the arm,
so it must not pace the servo loop) and each cycle carries its newest orientation and buttons.
The quaternion is taken as (w, x, y, z) of the handle in the device frame: unverified.

Limits: :data:`INVERSE3_PROFILE` (10 N, 1 N/mm, 0.006 N·s/mm: CHAI3D's Haply port), workspace
radius 150 mm (same source). It should move into ``haptics.profiles.PROFILES``.

Untested against hardware: the tests drive a fake of HaplyHardwareAPI's Python API.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np

from ....proto.frames import quat_matrix
from ...haptics.profiles import PROFILES
from ..base import (
    DeviceAccessDenied,
    DeviceDisconnected,
    DeviceError,
    DeviceInfo,
    DeviceNotFound,
    DeviceState,
    HapticDevice,
)
from ..udev import backend_access_help
from . import checked_force, import_vendor

EXTRA = "haply"
NATIVE_HINT = "HaplyHardwareAPI ships its native part in the wheel: reinstall it"

#: The Inverse3's limits (``haptics.profiles``: CHAI3D's Haply port's figures).
INVERSE3_PROFILE = PROFILES["inverse3"]
WORKSPACE_RADIUS_MM = 150.0
DEFAULT_WORKSPACE_CENTRE_M = (0.0186, -0.153, 0.151)
M_TO_MM = 1000.0
#: Haply's axes (x right, y away from the user, z up) → the common device frame (x toward the
#: user, y right, z up).
AXES = ((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
#: How long the wake-up exchange may take, s.
WAKEUP_TIMEOUT_S = 1.0


def _no_uuid(wakeup: object) -> bool:
    """Whether the wake-up reply carries the all-zero UUID the API returns when nothing
    answered."""
    ext = wakeup.get("device_id_ext") if isinstance(wakeup, Mapping) else None
    raw = getattr(ext, "bytes", None)
    if not callable(raw):
        return False
    try:
        return not any(raw())
    except Exception:  # an unexpected UUID type: do not judge by it
        return False


def quaternion_to_rotation(q: Sequence[float]) -> np.ndarray:
    """(3, 3) rotation matrix of the quaternion ``q`` = (w, x, y, z) (the VerseGrip's order;
    normalized first); identity for a zero or non-finite quaternion."""
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not math.isfinite(n) or n == 0.0:
        return np.eye(3)
    return quat_matrix((x, y, z, w))


def buttons_mask(buttons: object) -> int:
    """The VerseGrip's buttons as a bit mask: an int as is, a sequence of flags bit i = item
    i, a mapping by its values in key order."""
    if isinstance(buttons, bool):
        return int(buttons)
    if isinstance(buttons, int):
        return buttons & 0xFFFFFFFF
    if isinstance(buttons, Mapping):
        buttons = [buttons[k] for k in sorted(buttons)]
    if isinstance(buttons, Sequence):
        return sum(1 << i for i, pressed in enumerate(buttons) if pressed)
    return 0


class _HandleReader:
    """Polls a VerseGrip in its own thread; ``latest`` is (rotation (3, 3), buttons)."""

    def __init__(self, handle) -> None:
        self._handle = handle
        self.latest: tuple[np.ndarray, int] | None = None
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="versegrip", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                status = self._handle.GetVersegripStatus()
            except Exception as exc:  # reported by the device's cycle
                self.error = exc
                return
            if status:
                rotation = quaternion_to_rotation(status.get("quaternion", (1, 0, 0, 0)))
                self.latest = (rotation, buttons_mask(status.get("buttons", 0)))
            self._stop.wait(0.001)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)


class HaplyInverse3Device(HapticDevice):
    """A Haply Inverse3.

    Args:
        port: its serial port, or None to detect it.
        handle_port: the VerseGrip's serial port, ``"auto"`` to detect it, None for none.
        workspace_centre_m: (3,) our origin in the Inverse3's frame, m.
        serial_timeout_s: the API's read timeout per exchange after the wake-up, s (a timeout
            makes the API return an all-zero state, which ``cycle`` reports as a lost device).
    """

    def __init__(self, port: str | None = None, *, handle_port: str | None = None,
                 workspace_centre_m: Sequence[float] = DEFAULT_WORKSPACE_CENTRE_M,
                 serial_timeout_s: float = 0.1) -> None:
        super().__init__()
        centre = np.asarray(workspace_centre_m, dtype=float)
        if centre.shape != (3,) or not np.all(np.isfinite(centre)):
            raise ValueError("workspace_centre_m must be 3 finite numbers (m)")
        if not 0.0 < serial_timeout_s <= 10.0:
            raise ValueError(f"serial_timeout_s must be in (0, 10], got {serial_timeout_s!r}")
        self.port = port
        self.handle_port = handle_port
        self.serial_timeout_s = float(serial_timeout_s)
        self._centre_m = centre
        self.info = DeviceInfo(backend="haply", model="Inverse3", limits=INVERSE3_PROFILE,
                               workspace_radius_mm=WORKSPACE_RADIUS_MM, servo_rate_hz=1000.0,
                               buttons=0, sensed_rotation=False, axes=AXES)
        self._device = None
        self._stream = None
        self._port_in_use = ""
        self._handle: _HandleReader | None = None

    # -- connection ------------------------------------------------------------------------

    def _open(self) -> None:
        api = import_vendor("HaplyHardwareAPI", extra=EXTRA, native_hint=NATIVE_HINT)
        port = self.port or self._detect(api.detect_inverse3s, "Inverse3")
        self._check_port(port)
        try:
            self._stream = api.SerialStream(port)
            try:
                self._device = api.Inverse3(self._stream, WAKEUP_TIMEOUT_S)
            except TypeError:  # HaplyHardwareAPI before 0.1.13: no timeout argument
                self._device = api.Inverse3(self._stream)
            started = time.monotonic()
            wakeup = self._device.device_wakeup_dict()
            silent = time.monotonic() - started >= WAKEUP_TIMEOUT_S or _no_uuid(wakeup)
            if not silent and hasattr(self._device, "set_read_timeout"):
                self._device.set_read_timeout(self.serial_timeout_s)
        except Exception as exc:
            self._device = self._stream = None
            raise DeviceError(f"could not wake the Inverse3 on {port}: {exc}") from exc
        if silent:
            # The API does not raise on a timeout: it logs and returns uninitialised fields.
            self._device = self._stream = None
            raise DeviceNotFound(f"nothing answered the Inverse3 wake-up on {port} within "
                                 f"{WAKEUP_TIMEOUT_S} s (is it an Inverse3, powered on?)")
        serial = wakeup.get("device_id") if isinstance(wakeup, Mapping) else None
        self.info = replace(self.info, serial=None if serial is None else str(serial))
        self._port_in_use = port
        if self.handle_port is not None:
            self._open_handle(api)

    def _open_handle(self, api) -> None:
        port = (self._detect(api.detect_handles, "VerseGrip") if self.handle_port == "auto"
                else self.handle_port)
        self._check_port(port)
        try:
            handle = api.Handle(api.SerialStream(port))
        except Exception as exc:
            raise DeviceError(f"could not open the VerseGrip on {port}: {exc}") from exc
        self._handle = _HandleReader(handle)
        self.info = replace(self.info, buttons=3, sensed_rotation=True)

    @staticmethod
    def _detect(detect, what: str) -> str:
        try:
            ports = list(detect())
        except Exception as exc:
            raise DeviceError(f"HaplyHardwareAPI could not scan for an {what}: {exc}") from exc
        if not ports:
            raise DeviceNotFound(f"no Haply {what} found on any serial port (is it plugged in "
                                 "and powered?)")
        return str(ports[0])

    @staticmethod
    def _check_port(port: str) -> None:
        if os.path.exists(port) and not os.access(port, os.R_OK | os.W_OK):
            raise DeviceAccessDenied(f"{port}: " + backend_access_help("haply")
                                     + " (or: sudo usermod -aG dialout $USER)")

    def _close(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            handle.stop()
        # The force was zeroed by close() (HapticDevice.zero) before this.
        self._device = None
        self._stream = None  # the API closes the port when the stream is destroyed

    # -- I/O -------------------------------------------------------------------------------

    def cycle(self, force_N: np.ndarray) -> DeviceState:
        device = self._device
        if device is None:
            raise DeviceError("the Inverse3 is not open")
        f = checked_force(force_N, self.info.limits.max_force_N)
        try:
            position_m, velocity_m_s = device.end_effector_force(
                [float(f[0]), float(f[1]), float(f[2])])
        except Exception as exc:
            if not os.path.exists(self._port_in_use):
                raise DeviceDisconnected(f"the Inverse3 on {self._port_in_use} is gone: "
                                         f"{exc}") from exc
            raise DeviceError(f"Inverse3 exchange failed: {exc}") from exc
        t_ns = time.monotonic_ns()
        position = np.asarray(position_m, dtype=float)
        velocity = np.asarray(velocity_m_s, dtype=float)
        if position.shape != (3,) or velocity.shape != (3,):
            raise DeviceError("the Inverse3 answered a malformed state "
                              f"({position_m!r}, {velocity_m_s!r})")
        # On a timeout the API logs and returns zeros instead of raising. The base origin is
        # outside the reachable workspace, so an all-zero state is no answer.
        if not (np.any(position) or np.any(velocity)):
            gone = "" if os.path.exists(self._port_in_use) else " (its port is gone)"
            raise DeviceDisconnected(f"the Inverse3 on {self._port_in_use} did not answer "
                                     f"within its {self.serial_timeout_s} s timeout{gone}")
        position_mm = (position - self._centre_m) * M_TO_MM
        velocity_mm_s = velocity * M_TO_MM
        rotation, buttons = None, 0
        if self._handle is not None:
            if self._handle.error is not None:
                raise DeviceError(f"VerseGrip read failed: {self._handle.error!r}")
            if self._handle.latest is not None:
                rotation, buttons = self._handle.latest
                rotation = rotation.copy()
        return DeviceState(position_mm=position_mm, velocity_mm_s=velocity_mm_s,
                           buttons=buttons, t_ns=t_ns, rotation=rotation)
