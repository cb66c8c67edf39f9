"""3D Systems Touch (and other OpenHaptics devices) through the HD API, via ``pyOpenHaptics``.

Install: ``pip install 'burrforce[openhaptics]'`` plus 3D Systems' OpenHaptics (``libHD.so``
on the loader path) and the Touch device driver (which configures the device; the USB Touch is
a CDC-ACM serial port, so on Linux its ``/dev/ttyACM*`` needs a udev rule, ``devices.udev``).

How :meth:`OpenHapticsDevice.cycle` maps onto OpenHaptics: the HD API runs its own servo loop (the
scheduler thread, 1 kHz) and only lets the application touch the device inside a scheduler
callback's frame. So the back-end registers one asynchronous callback which, every servo tick,
reads the transform, velocity and buttons, writes the newest commanded force and publishes the
reading. ``cycle(force)`` stores the command (taken by the next tick, ≤ 1 ms later) and returns
the newest published reading (≤ 1 ms old). Two watchdogs: the callback renders zero when no
``cycle`` came for ``stale_after_s`` (the device loop stalled: the device must not keep the
last force), and ``cycle`` raises DeviceDisconnected when the scheduler has not ticked for
``scheduler_timeout_s`` (an HD error ends pyOpenHaptics' callback; the device was unplugged).

Frame: OpenHaptics' own axes, x to the operator's right, y up, z toward the operator
(right-handed), in mm and mm/s; the origin is moved to the centre of the device's usable
workspace box (``HD_USABLE_WORKSPACE_DIMENSIONS``) unless ``workspace_centre_mm`` is given.
The rotation is the stylus gimbal's (``HD_CURRENT_TRANSFORM``). Forces in N.

Limits: ``PROFILES["touch"]`` (3.3 N); workspace radius 75 mm (CHAI3D's Touch figure).

Untested against hardware: the tests drive a fake of pyOpenHaptics' Python API.
"""

from __future__ import annotations

import contextlib
import ctypes
import io
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from ...haptics.profiles import PROFILES
from ...haptics.velocity import DeviceVelocity
from ..base import (
    DeviceDisconnected,
    DeviceError,
    DeviceInfo,
    DeviceNotFound,
    DeviceState,
    HapticDevice,
)
from ..udev import backend_access_help
from . import checked_force, import_vendor

EXTRA = "openhaptics"
NATIVE_HINT = ("install 3D Systems OpenHaptics for Linux and the Touch device driver, and "
               "make libHD.so loadable (e.g. export LD_LIBRARY_PATH=/usr/lib64 or run ldconfig)")
WORKSPACE_RADIUS_MM = 75.0
#: OpenHaptics' axes (x right, y up, z toward the user) → the common device frame (x toward the
#: user, y right, z up).
AXES = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
_ZERO = np.zeros(3)


class _Reading(NamedTuple):
    position_mm: np.ndarray
    velocity_mm_s: np.ndarray
    buttons: int
    rotation: np.ndarray
    t_ns: int


class OpenHapticsDevice(HapticDevice):
    """An OpenHaptics device (3D Systems Touch, Touch X, Phantom Omni ...).

    Args:
        device_name: the device's name in the Touch Setup configuration.
        workspace_centre_mm: (3,) the origin of our frame in OpenHaptics' frame, mm; None:
            the centre of the device's usable workspace box.
        stale_after_s: the servo callback renders zero when the newest command is older.
        scheduler_timeout_s: ``cycle`` raises DeviceDisconnected when the newest servo
            reading is older.
        first_state_timeout_s: how long ``open`` waits for the first servo tick.
    """

    def __init__(self, device_name: str = "Default Device", *,
                 workspace_centre_mm: Sequence[float] | None = None,
                 stale_after_s: float = 0.05, scheduler_timeout_s: float = 0.25,
                 first_state_timeout_s: float = 2.0) -> None:
        super().__init__()
        for name, value in (("stale_after_s", stale_after_s),
                            ("scheduler_timeout_s", scheduler_timeout_s),
                            ("first_state_timeout_s", first_state_timeout_s)):
            if not (isinstance(value, (int, float)) and 0.0 < value < 60.0):
                raise ValueError(f"{name} must be in (0, 60) s, got {value!r}")
        if workspace_centre_mm is not None:
            workspace_centre_mm = np.asarray(workspace_centre_mm, dtype=float)
            if workspace_centre_mm.shape != (3,) or not np.all(np.isfinite(workspace_centre_mm)):
                raise ValueError("workspace_centre_mm must be 3 finite numbers (mm)")
        self.device_name = device_name
        self._centre = workspace_centre_mm
        self._stale_ns = int(stale_after_s * 1e9)
        self._scheduler_timeout_ns = int(scheduler_timeout_s * 1e9)
        self._first_state_timeout_s = float(first_state_timeout_s)
        self.info = DeviceInfo(backend="openhaptics", model="Touch", limits=PROFILES["touch"],
                               workspace_radius_mm=WORKSPACE_RADIUS_MM, servo_rate_hz=1000.0,
                               buttons=2, sensed_rotation=True, axes=AXES)
        self._reset()

    def _reset(self) -> None:
        # Shared with the scheduler thread: each is replaced whole (one reference store, atomic
        # under the GIL), never mutated in place.
        self._command: tuple[np.ndarray, int] = (_ZERO, 0)
        self._latest: _Reading | None = None
        self._servo_error: BaseException | None = None
        self._closing = False
        self._ticks = 0
        self._model: str | None = None
        self._estimate = DeviceVelocity(PROFILES["touch"].resolution_mm)
        self._device = None
        self._callback = None

    # -- connection ------------------------------------------------------------------------

    def _open(self) -> None:
        hd = import_vendor("pyOpenHaptics.hd", extra=EXTRA, native_hint=NATIVE_HINT)
        hd_device = import_vendor("pyOpenHaptics.hd_device", extra=EXTRA,
                                  native_hint=NATIVE_HINT)
        hd_callback = import_vendor("pyOpenHaptics.hd_callback", extra=EXTRA,
                                    native_hint=NATIVE_HINT)
        self._reset()
        self._hd = hd
        # The ctypes callback object must outlive the scheduler's use of it.
        self._callback = hd_callback.hd_callback(self._servo_tick)
        said = io.StringIO()  # pyOpenHaptics prints its progress; keep it for our messages
        with contextlib.redirect_stdout(said):
            device = hd_device.HapticDevice(self._callback, self.device_name, "async")
        if device.id is None:  # pyOpenHaptics returns None when hdInitDevice failed
            with contextlib.redirect_stdout(io.StringIO()):
                hd.stop_scheduler()
            raise DeviceNotFound(
                f"OpenHaptics could not initialise the device {self.device_name!r} "
                f"({' '.join(said.getvalue().split())}); check it in Touch_Setup / "
                "Touch_Diagnostic. " + backend_access_help("openhaptics"))
        self._device = device
        deadline = time.monotonic() + self._first_state_timeout_s
        while self._latest is None and self._servo_error is None:
            if time.monotonic() > deadline:
                self._stop_device()
                raise DeviceError("the OpenHaptics scheduler never ran the servo callback "
                                  f"within {self._first_state_timeout_s} s")
            time.sleep(0.001)
        if self._servo_error is not None:
            error = self._servo_error
            self._stop_device()
            raise DeviceError(f"the OpenHaptics servo callback failed: {error!r}") from error
        self.info = replace(self.info, model=self._model or self.info.model)

    def _close(self) -> None:
        if self._device is None:  # never started, or _open stopped it already
            return
        self._closing = True  # the servo callback renders zero from now on
        ticks = self._ticks
        deadline = time.monotonic() + 0.2
        while self._ticks < ticks + 2 and time.monotonic() < deadline:
            time.sleep(0.001)
        self._stop_device()

    def _stop_device(self) -> None:
        device, self._device = self._device, None
        if device is not None:
            with contextlib.redirect_stdout(io.StringIO()):
                device.close()  # hdStopScheduler + hdDisableDevice

    # -- the servo callback (OpenHaptics' scheduler thread, inside an HD frame) -------------

    def _servo_tick(self) -> None:
        hd = self._hd
        try:
            now = time.monotonic_ns()
            force, t_command = self._command
            if self._closing or self._servo_error is not None or now - t_command > self._stale_ns:
                force = _ZERO
            hd.set_force([float(force[0]), float(force[1]), float(force[2])])
            if self._servo_error is not None:
                return
            if self._latest is None:
                self._first_tick(hd)
            m = hd.get_transform()  # column-major 4×4: m[column][row], translation m[3]
            position = np.array((m[3][0], m[3][1], m[3][2]), dtype=float) - self._centre
            rotation = np.array([[m[c][r] for c in range(3)] for r in range(3)], dtype=float)
            velocity = self._velocity(hd, position, now)
            self._latest = _Reading(position, velocity, int(hd.get_buttons()), rotation, now)
        except BaseException as exc:  # an exception must not leave the C callback
            self._servo_error = exc
            with contextlib.suppress(Exception):
                hd.set_force([0.0, 0.0, 0.0])
        finally:
            self._ticks += 1

    def _first_tick(self, hd) -> None:
        with contextlib.suppress(Exception):
            self._model = hd.get_model()
        if self._centre is None:
            box = self._get_doublev(hd, "HD_USABLE_WORKSPACE_DIMENSIONS", ctypes.c_double * 6)
            box_mm = np.zeros(6) if box is None else np.array(box[0:6], dtype=float)
            self._centre = 0.5 * (box_mm[0:3] + box_mm[3:6])

    def _velocity(self, hd, position: np.ndarray, now: int) -> np.ndarray:
        """OpenHaptics' own velocity estimate (mm/s), or the project's FOAW estimate from the
        positions when the wrapper does not expose ``hdGetDoublev``."""
        measured = self._get_doublev(hd, "HD_CURRENT_VELOCITY", getattr(hd, "hduVector3Dd", None))
        if measured is not None:
            return np.array(measured[0:3], dtype=float)
        return self._estimate.update(position, now * 1e-9).copy()

    @staticmethod
    def _get_doublev(hd, code_name: str, ctype):
        # pyOpenHaptics exposes hdGetDoublev only as the private helper ``_get_doublev``.
        getter = getattr(hd, "_get_doublev", None)
        code = getattr(hd, code_name, None)
        if getter is None or code is None or ctype is None:
            return None
        return getter(code, ctype)

    # -- I/O -------------------------------------------------------------------------------

    def cycle(self, force_N: np.ndarray) -> DeviceState:
        if self._device is None:
            raise DeviceError("the OpenHaptics device is not open")
        f = checked_force(force_N, self.info.limits.max_force_N)
        now = time.monotonic_ns()
        self._command = (f, now)
        if self._servo_error is not None:
            raise DeviceError(f"the OpenHaptics servo callback failed: {self._servo_error!r}")
        reading = self._latest
        if reading is None or now - reading.t_ns > self._scheduler_timeout_ns:
            age = "never" if reading is None else f"{(now - reading.t_ns) / 1e6:.0f} ms ago"
            raise DeviceDisconnected(
                f"the OpenHaptics scheduler last ran the servo callback {age} (an HD error "
                "stops it, e.g. the device was unplugged or exceeded its force/velocity limits)")
        return DeviceState(position_mm=reading.position_mm.copy(),
                           velocity_mm_s=reading.velocity_mm_s.copy(), buttons=reading.buttons,
                           t_ns=reading.t_ns, rotation=reading.rotation.copy())

    @property
    def ticks(self) -> int:
        """Servo callbacks run since ``open``."""
        return self._ticks
