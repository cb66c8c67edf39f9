"""Force Dimension devices (omega.x, delta.x, sigma.x, lambda.x; the Falcon too) through the
Force Dimension SDK, via the ``forcedimension-core`` package (ctypes over ``libdrd``).

Install: ``pip install 'burrforce[forcedimension]'`` (forcedimension-core needs Python < 3.13)
plus the Force Dimension SDK, with ``FDSDK`` set to its folder (the package loads
``$FDSDK/lib/release/lin-<arch>-gcc/libdrd.so.*``; ``/usr/local/lib`` and ``~/.local/lib`` are
searched too). On Linux the device node also needs a udev rule (``devices.udev``).

Frame: the SDK's own, unchanged apart from units: origin at the centre of the workspace, x
toward the operator, y to the operator's right, z up (right-handed). The SDK reports m and
m/s; this back-end reports mm and mm/s and takes N. The SDK's gravity compensation stays on
(its default), so the commanded force adds to it.

One :meth:`ForceDimensionDevice.cycle` = ``dhdSetForce`` + ``dhdGetPosition`` +
``dhdGetLinearVelocity`` (the SDK's windowed estimate) + ``dhdGetButtonMask`` (+
``dhdGetOrientationFrame`` on devices with a wrist). :meth:`~ForceDimensionDevice.home` runs
the SDK's automatic initialisation (``drdAutoInit``), during which the device moves by itself.

Limits: ``PROFILES["falcon"]`` for a Falcon, ``PROFILES["omega3"]`` for every other model
(conservative for the 20 N delta/sigma/lambda devices, until they have profiles). Workspace
radii are CHAI3D's figures per model.

Untested against hardware: the tests drive a fake of forcedimension-core's Python API.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from ...haptics.profiles import PROFILES
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

EXTRA = "forcedimension"
NATIVE_HINT = ("install the Force Dimension SDK (forcedimension.com → Download) and set "
               "FDSDK to its folder, e.g. export FDSDK=$HOME/sdk-3.17.6")

#: Workspace radius (mm) by the SDK's device type name (CHAI3D 3.2 ``CDeltaDevices.cpp``).
_WORKSPACE_RADIUS_MM = {"DELTA3": 150.0, "FALCON": 40.0}
_DEFAULT_WORKSPACE_RADIUS_MM = 75.0
#: SDK error names that mean the device went away, not a bad call.
_GONE = {"COM", "TIMEOUT", "NO_DEVICE_FOUND", "DEVICE_NOT_READY"}
M_TO_MM = 1000.0


def _load():
    """(dhd, drd, constants) modules of forcedimension-core."""
    dhd = import_vendor("forcedimension_core.dhd", extra=EXTRA, native_hint=NATIVE_HINT)
    drd = import_vendor("forcedimension_core.drd", extra=EXTRA, native_hint=NATIVE_HINT)
    constants = import_vendor("forcedimension_core.constants", extra=EXTRA,
                              native_hint=NATIVE_HINT)
    return dhd, drd, constants


class ForceDimensionDevice(HapticDevice):
    """A Force Dimension device.

    Args:
        index: which device (the SDK's enumeration index), or None for the first available.
        velocity_window_ms: the SDK's velocity-estimator window, ms.
    """

    def __init__(self, index: int | None = None, *, velocity_window_ms: int = 20) -> None:
        super().__init__()
        if index is not None and not 0 <= index < 128:
            raise ValueError(f"index must be 0..127 or None, got {index!r}")
        if not 1 <= velocity_window_ms <= 1000:
            raise ValueError(f"velocity_window_ms must be 1..1000, got {velocity_window_ms!r}")
        self.index = index
        self.velocity_window_ms = int(velocity_window_ms)
        self.info = DeviceInfo(backend="forcedimension", model="Force Dimension device",
                               limits=PROFILES["omega3"],
                               workspace_radius_mm=_DEFAULT_WORKSPACE_RADIUS_MM,
                               servo_rate_hz=1000.0, buttons=1)
        self._id = -1
        self._wrist = False
        self._buf = [0.0, 0.0, 0.0]
        self._frame = [[0.0] * 3 for _ in range(3)]

    # -- connection ------------------------------------------------------------------------

    def _open(self) -> None:
        dhd, drd, constants = _load()
        self._dhd, self._drd, self._constants = dhd, drd, constants
        if dhd.getDeviceCount() <= 0:
            raise DeviceNotFound("no Force Dimension device found (is it plugged in and "
                                 "powered?); on Linux it may also be a missing udev rule: "
                                 + backend_access_help("forcedimension"))
        ident = drd.open() if self.index is None else drd.openID(self.index)
        if ident < 0:
            raise self._error("could not open the Force Dimension device", opening=True)
        self._id = ident
        self._configure()  # if it raises, open() has _close release the device

    def _configure(self) -> None:
        dhd, drd, constants = self._dhd, self._drd, self._constants
        ident = self._id
        try:
            kind = constants.DeviceType(dhd.getSystemType(ident)).name
        except ValueError:  # a model newer than the wrapper's table
            kind = "UNKNOWN"
        name = dhd.getSystemName(ident) or kind.lower()
        serial = dhd.getSerialNumber(ident)
        self._wrist = bool(dhd.hasWrist(ident))
        is_falcon = kind == "FALCON"
        self.info = replace(
            self.info, model=name,
            limits=PROFILES["falcon" if is_falcon else "omega3"],
            workspace_radius_mm=_WORKSPACE_RADIUS_MM.get(kind, _DEFAULT_WORKSPACE_RADIUS_MM),
            buttons=4 if is_falcon else 1, sensed_rotation=self._wrist,
            serial=None if serial < 0 else str(serial))
        # drdAutoInit leaves the DRD regulation thread running; our loop owns the device.
        if drd.isRunning(ident) and drd.stop(True, ident) < 0:
            raise self._error("could not stop the SDK's regulation thread")
        if dhd.configLinearVelocity(self.velocity_window_ms,
                                    constants.VelocityEstimatorMode.WINDOWING, ident) < 0:
            raise self._error("could not configure the velocity estimator")
        if dhd.enableForce(True, ident) < 0:
            raise self._error("could not enable forces")

    def _close(self) -> None:  # the force was zeroed by close() (HapticDevice.zero)
        if self._id >= 0:
            try:
                self._drd.close(self._id)
            finally:
                self._id = -1

    def home(self, timeout_s: float = 30.0,
             progress: Callable[[str], None] | None = None,
             cancelled: Callable[[], bool] | None = None) -> bool:
        """Run the SDK's automatic initialisation if the device is not initialised yet. It
        blocks until done (neither ``timeout_s`` nor ``cancelled`` can interrupt it); the
        device moves by itself."""
        if not self.is_open:
            raise DeviceError("open the device before homing it")
        drd, ident = self._drd, self._id
        if drd.isInitialized(ident):
            return True
        if progress is not None:
            progress("Force Dimension auto-initialisation: the device moves by itself to its "
                     "end stops; keep hands off the handle until it stops.")
        if drd.autoInit(ident) < 0:
            raise self._error("automatic initialisation failed")
        if drd.isRunning(ident) and drd.stop(True, ident) < 0:
            raise self._error("could not stop the SDK's regulation thread")
        return bool(drd.isInitialized(ident))

    # -- I/O -------------------------------------------------------------------------------

    def cycle(self, force_N: np.ndarray) -> DeviceState:
        if self._id < 0:
            raise DeviceError("the Force Dimension device is not open")
        dhd, ident, buf = self._dhd, self._id, self._buf
        f = checked_force(force_N, self.info.limits.max_force_N)
        if dhd.setForce((float(f[0]), float(f[1]), float(f[2])), ident) < 0:
            raise self._error("dhdSetForce failed")
        if dhd.getPosition(buf, ident) < 0:
            raise self._error("dhdGetPosition failed")
        position_mm = np.array(buf) * M_TO_MM
        t_ns = time.monotonic_ns()
        if dhd.getLinearVelocity(buf, ident) < 0:
            # The estimator needs two readings within its window: none yet is not a fault.
            if self._error_name() != "TIMEOUT":
                raise self._error("dhdGetLinearVelocity failed")
            velocity_mm_s = np.zeros(3)
        else:
            velocity_mm_s = np.array(buf) * M_TO_MM
        buttons = int(dhd.getButtonMask(ident)) & 0xFFFFFFFF
        rotation = None
        if self._wrist:
            if dhd.getOrientationFrame(self._frame, ident) < 0:
                raise self._error("dhdGetOrientationFrame failed")
            rotation = np.array(self._frame, dtype=float)
        return DeviceState(position_mm=position_mm, velocity_mm_s=velocity_mm_s,
                           buttons=buttons, t_ns=t_ns, rotation=rotation)

    # -- errors ----------------------------------------------------------------------------

    def _error_name(self) -> str:
        try:
            return self._constants.ErrorNum(self._dhd.errorGetLast()).name
        except ValueError:
            return "ERROR"

    def _error(self, what: str, *, opening: bool = False) -> DeviceError:
        name = self._error_name()
        text = f"{what}: {self._dhd.errorGetLastStr()} ({name})"
        if opening and name == "NO_DEVICE_FOUND":
            return DeviceNotFound(text + "; " + backend_access_help("forcedimension"))
        if opening and name == "DEVICE_IN_USE":
            return DeviceError(text + "; another program holds the device")
        if not opening and name in _GONE:
            return DeviceDisconnected(text)
        return DeviceError(text)
