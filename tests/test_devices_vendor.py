"""Vendor back-ends (Force Dimension, OpenHaptics, Haply) against fakes of the vendors' Python
APIs: the same module, function and class names and signatures as forcedimension-core 1.0.0,
pyOpenHaptics 1.0.1 and HaplyHardwareAPI 0.1.13 (read from their wheels), backed by a
simulated device. They check our side only — units, axes, clamping, zeroing, error
messages — never the vendors' libraries or hardware."""

from __future__ import annotations

import ctypes
import gc
import math
import os
import sys
import threading
import time
import types
import weakref
from enum import IntEnum

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.base import (
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    VendorLibraryMissing,
)
from burrforce.server.devices.vendor.forcedimension import ForceDimensionDevice
from burrforce.server.devices.vendor.haply import (
    INVERSE3_PROFILE,
    HaplyInverse3Device,
    buttons_mask,
    quaternion_to_rotation,
)
from burrforce.server.devices.vendor.openhaptics import OpenHapticsDevice
from burrforce.server.haptics.profiles import PROFILES


def wait_for(predicate, timeout_s: float = 5.0) -> bool:
    """Poll ``predicate`` until true; generous timeout, no upper timing bound asserted."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.001)
    return predicate()


def install(monkeypatch, modules: dict[str, types.ModuleType]) -> None:
    for name, module in modules.items():
        monkeypatch.setitem(sys.modules, name, module)


def block(monkeypatch, *names: str) -> None:
    """Make ``import name`` fail as for an uninstalled package."""
    for name in names:
        monkeypatch.setitem(sys.modules, name, None)


# ---------------------------------------------------------------------------------------------
# forcedimension_core fake (forcedimension_core 1.0.0: dhd, drd, constants)


class DeviceType(IntEnum):
    NONE = 0
    DELTA3 = 63
    OMEGA3 = 33
    OMEGA7_RIGHT = 35
    FALCON = 60


class ErrorNum(IntEnum):
    NO_ERROR = 0
    ERROR = 1
    COM = 2
    NO_DEVICE_FOUND = 5
    TIMEOUT = 7
    DEVICE_IN_USE = 20


class VelocityEstimatorMode(IntEnum):
    WINDOWING = 0


class FakeFD:
    """A simulated Force Dimension device, SI units (m, m/s, N) as the SDK reports them."""

    def __init__(self, kind=DeviceType.OMEGA3, name="omega.3", count=1, wrist=False):
        self.kind, self.name, self.count, self.wrist = kind, name, count, wrist
        self.position_m = [0.0, 0.0, 0.0]
        self.velocity_m_s = [0.0, 0.0, 0.0]
        self.velocity_ready = True
        self.frame = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        self.buttons = 0
        self.force = None
        self.force_enabled = False
        self.initialized = True
        self.running = False
        self.opened = False
        self.error = ErrorNum.NO_ERROR
        self.fail_set_force = False
        self.calls: list[str] = []

    def modules(self) -> dict[str, types.ModuleType]:
        dev = self
        constants = types.ModuleType("forcedimension_core.constants")
        constants.DeviceType = DeviceType
        constants.ErrorNum = ErrorNum
        constants.VelocityEstimatorMode = VelocityEstimatorMode
        constants.TIMEGUARD = 1
        constants.MOTOR_SATURATED = 2

        dhd = types.ModuleType("forcedimension_core.dhd")

        def fail(err):
            dev.error = err
            return -1

        def getDeviceCount() -> int:
            return dev.count

        def getSystemType(ID: int = -1):
            return DeviceType(dev.kind)

        def getSystemName(ID: int = -1):
            return dev.name

        def getSerialNumber(ID: int = -1) -> int:
            return 1234

        def hasWrist(ID: int = -1) -> bool:
            return dev.wrist

        def configLinearVelocity(ms=20, mode=VelocityEstimatorMode.WINDOWING, ID=-1) -> int:
            dev.calls.append(f"configLinearVelocity({ms})")
            return 0

        def enableForce(enable: bool, ID: int = -1) -> int:
            dev.force_enabled = bool(enable)
            return 0

        def setForce(f, ID: int = -1) -> int:
            if dev.fail_set_force:
                return fail(ErrorNum.COM)
            dev.force = (f[0], f[1], f[2])
            return 0

        def getPosition(out, ID: int = -1) -> int:
            out[0], out[1], out[2] = dev.position_m
            return 0

        def getLinearVelocity(out, ID: int = -1) -> int:
            if not dev.velocity_ready:
                return fail(ErrorNum.TIMEOUT)
            out[0], out[1], out[2] = dev.velocity_m_s
            return 0

        def getButtonMask(ID: int = -1) -> int:
            return dev.buttons

        def getOrientationFrame(out, ID: int = -1) -> int:
            for i in range(3):
                for j in range(3):
                    out[i][j] = dev.frame[i][j]
            return 0

        def errorGetLast():
            return dev.error

        def errorGetLastStr() -> str:
            return dev.error.name.lower().replace("_", " ")

        def close(ID: int = -1) -> int:
            dev.opened = False
            return 0

        for fn in (getDeviceCount, getSystemType, getSystemName, getSerialNumber, hasWrist,
                   configLinearVelocity, enableForce, setForce, getPosition,
                   getLinearVelocity, getButtonMask, getOrientationFrame, errorGetLast,
                   errorGetLastStr, close):
            setattr(dhd, fn.__name__, fn)

        drd = types.ModuleType("forcedimension_core.drd")

        def drd_open() -> int:
            if dev.count <= 0:
                return fail(ErrorNum.NO_DEVICE_FOUND)
            dev.opened = True
            return 0

        def openID(ID: int) -> int:
            return drd_open() if ID < dev.count else fail(ErrorNum.NO_DEVICE_FOUND)

        def drd_close(ID: int = -1) -> int:
            dev.opened = False
            dev.calls.append("drd.close")
            return 0

        def isRunning(ID: int = -1) -> bool:
            return dev.running

        def isInitialized(ID: int = -1) -> bool:
            return dev.initialized

        def autoInit(ID: int = -1) -> int:
            dev.calls.append("autoInit")
            dev.initialized = True
            dev.running = True
            return 0

        def stop(force_on: bool, ID: int = -1) -> int:
            dev.calls.append(f"stop({force_on})")
            dev.running = False
            return 0

        drd.open, drd.openID, drd.close = drd_open, openID, drd_close
        drd.isRunning, drd.isInitialized, drd.autoInit, drd.stop = (isRunning, isInitialized,
                                                                    autoInit, stop)
        package = types.ModuleType("forcedimension_core")
        package.__path__ = []
        package.dhd, package.drd, package.constants = dhd, drd, constants
        return {"forcedimension_core": package, "forcedimension_core.dhd": dhd,
                "forcedimension_core.drd": drd, "forcedimension_core.constants": constants}


@pytest.fixture
def fd(monkeypatch):
    fake = FakeFD()
    install(monkeypatch, fake.modules())
    return fake


def test_fd_units_axes_and_info(fd):
    fd.position_m = [0.010, -0.020, 0.030]
    fd.velocity_m_s = [0.1, 0.0, -0.2]
    fd.buttons = 0b1
    with ForceDimensionDevice() as dev:
        state = dev.cycle(np.array([1.0, 2.0, 3.0]))
        assert fd.force == (1.0, 2.0, 3.0) and fd.force_enabled
        np.testing.assert_allclose(state.position_mm, [10.0, -20.0, 30.0])
        np.testing.assert_allclose(state.velocity_mm_s, [100.0, 0.0, -200.0])
        assert state.buttons == 1 and state.rotation is None and state.t_ns > 0
        assert dev.info.model == "omega.3" and dev.info.serial == "1234"
        assert dev.info.limits is PROFILES["omega3"]
        assert dev.info.workspace_radius_mm == 75.0 and not dev.info.sensed_rotation
    assert "configLinearVelocity(20)" in fd.calls


def test_fd_falcon_and_wrist_models(monkeypatch):
    falcon = FakeFD(kind=DeviceType.FALCON, name="Falcon")
    install(monkeypatch, falcon.modules())
    with ForceDimensionDevice() as dev:
        assert dev.info.limits is PROFILES["falcon"] and dev.info.buttons == 4
        assert dev.info.workspace_radius_mm == 40.0
    omega7 = FakeFD(kind=DeviceType.OMEGA7_RIGHT, name="omega.7", wrist=True)
    omega7.frame = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    install(monkeypatch, omega7.modules())
    with ForceDimensionDevice() as dev:
        assert dev.info.sensed_rotation
        np.testing.assert_array_equal(dev.cycle(np.zeros(3)).rotation, omega7.frame)


def test_fd_clamps_to_profile_and_close_zeroes(fd):
    dev = ForceDimensionDevice()
    dev.open()
    dev.cycle(np.array([30.0, 40.0, 0.0]))  # 50 N → 12 N along the same direction
    np.testing.assert_allclose(fd.force, [12.0 * 0.6, 12.0 * 0.8, 0.0])
    dev.cycle(np.array([np.nan, 0.0, 0.0]))
    assert fd.force == (0.0, 0.0, 0.0)
    dev.cycle(np.array([1.0, 0.0, 0.0]))
    dev.close()
    assert fd.force == (0.0, 0.0, 0.0) and not fd.opened and "drd.close" in fd.calls
    dev.close()  # twice is fine


def test_fd_velocity_estimator_not_ready_is_zero(fd):
    fd.velocity_ready = False
    with ForceDimensionDevice() as dev:
        np.testing.assert_array_equal(dev.cycle(np.zeros(3)).velocity_mm_s, np.zeros(3))


def test_fd_disconnect_and_not_found(fd):
    with ForceDimensionDevice() as dev:
        fd.fail_set_force = True
        with pytest.raises(DeviceDisconnected, match="com"):
            dev.cycle(np.zeros(3))
    fd.fail_set_force = False
    fd.count = 0
    with pytest.raises(DeviceNotFound, match='idVendor}=="1451"'):
        ForceDimensionDevice().open()


def test_fd_home_runs_auto_init_and_stops_regulation(fd):
    fd.initialized = False
    messages = []
    with ForceDimensionDevice() as dev:
        assert dev.home(progress=messages.append)
    assert fd.calls.index("autoInit") < fd.calls.index("stop(True)")
    assert "keep hands off" in messages[0]


def test_fd_bad_force_shape(fd):
    with ForceDimensionDevice() as dev, pytest.raises(ValueError, match=r"\(3,\)"):
        dev.cycle(np.zeros(2))


def test_fd_package_missing(monkeypatch):
    block(monkeypatch, "forcedimension_core", "forcedimension_core.dhd")
    with pytest.raises(VendorLibraryMissing) as err:
        ForceDimensionDevice().open()
    assert "pip install 'burrforce[forcedimension]'" in str(err.value)
    assert "FDSDK" in str(err.value)


def test_fd_native_sdk_missing(monkeypatch, tmp_path):
    # forcedimension-core raises ImportError at import when libdrd cannot be loaded.
    package = tmp_path / "forcedimension_core"
    package.mkdir()
    (package / "__init__.py").write_text(
        'raise ImportError("There were problems loading libdrd.")\n')
    for name in [m for m in sys.modules if m.startswith("forcedimension_core")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(VendorLibraryMissing, match=r"native library.*libdrd.*FDSDK"):
        ForceDimensionDevice().open()


# ---------------------------------------------------------------------------------------------
# pyOpenHaptics fake (pyOpenHaptics 1.0.1: hd, hd_device.HapticDevice, hd_callback)

HD_CALLBACK_DONE, HD_CALLBACK_CONTINUE = 0, 1
hduMatrix = (ctypes.c_double * 4) * 4
hduVector3Dd = ctypes.c_double * 3


class FakeTouch:
    """A simulated OpenHaptics device plus its scheduler thread (OpenHaptics' frame, mm)."""

    def __init__(self, init_ok: bool = True):
        self.init_ok = init_ok
        self.position_mm = [0.0, 0.0, 0.0]
        self.rotation = np.eye(3)
        self.velocity_mm_s = [0.0, 0.0, 0.0]
        self.buttons = 0
        self.box_mm = [-80.0, -60.0, -35.0, 80.0, 60.0, 35.0]
        self.force = [0.0, 0.0, 0.0]
        self.enabled = False
        self.paused = False
        self.callbacks = []
        self._thread = None
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.is_set():
            if not self.paused:
                for cb in list(self.callbacks):
                    if cb(None) == HD_CALLBACK_DONE:
                        self.callbacks.remove(cb)
            time.sleep(0.0005)

    def modules(self) -> dict[str, types.ModuleType]:
        dev = self
        hd = types.ModuleType("pyOpenHaptics.hd")
        hd.HD_CURRENT_VELOCITY = 0x2051
        hd.HD_USABLE_WORKSPACE_DIMENSIONS = 0x2551
        hd.hduMatrix, hd.hduVector3Dd = hduMatrix, hduVector3Dd

        def _get_doublev(code: int, dtype):
            values = {0x2051: dev.velocity_mm_s, 0x2551: dev.box_mm}[code]
            return dtype(*values)

        def init_device(name: str = "Default Device") -> int:
            if dev.init_ok:
                return 0
            print("Unable to initialize the device. Check the connection!")
            return None

        def get_buttons() -> int:
            return dev.buttons

        def get_transform():
            m = hduMatrix()
            for col in range(3):
                for row in range(3):
                    m[col][row] = dev.rotation[row, col]
                m[3][col] = dev.position_mm[col]
            m[3][3] = 1.0
            return m

        def get_error() -> bool:
            return False

        def set_force(feedback) -> None:
            dev.force = list(feedback)

        def close_device(id: int):
            dev.enabled = False

        def get_current_device() -> int:
            return 0

        def start_scheduler() -> None:
            dev._stop.clear()
            dev._thread = threading.Thread(target=dev._run, daemon=True)
            dev._thread.start()

        def stop_scheduler() -> None:
            dev._stop.set()
            if dev._thread is not None:
                dev._thread.join()
                dev._thread = None

        def enable_force() -> None:
            dev.enabled = True
            print("Force feedback enabled!")

        def begin_frame(id: int) -> None:
            pass

        def end_frame(id: int) -> None:
            pass

        def get_model() -> str:
            return "Touch"

        def get_vendor() -> str:
            return "3D Systems"

        for fn in (_get_doublev, init_device, get_buttons, get_transform, get_error, set_force,
                   close_device, get_current_device, start_scheduler, stop_scheduler,
                   enable_force, begin_frame, end_frame, get_model, get_vendor):
            setattr(hd, fn.__name__, fn)

        hd_callback_mod = types.ModuleType("pyOpenHaptics.hd_callback")

        def hd_callback(input_function):
            @ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.POINTER(ctypes.c_void_p))
            def _callback(pUserData):
                begin_frame(get_current_device())
                input_function()
                end_frame(get_current_device())
                if get_error():
                    return HD_CALLBACK_DONE
                return HD_CALLBACK_CONTINUE
            return _callback

        def hdAsyncSheduler(callback):
            dev.callbacks.append(callback)

        def hdSyncSheduler(callback):
            callback(None)

        hd_callback_mod.hd_callback = hd_callback
        hd_callback_mod.hdAsyncSheduler = hdAsyncSheduler
        hd_callback_mod.hdSyncSheduler = hdSyncSheduler

        hd_device = types.ModuleType("pyOpenHaptics.hd_device")

        class HapticDevice:
            def __init__(self, callback, device_name: str = "Default Device",
                         scheduler_type: str = "async"):
                print(f"Initializing haptic device with name {device_name}")
                self.id = init_device(device_name)
                enable_force()
                start_scheduler()
                self.scheduler(callback, scheduler_type)

            def close(self):
                stop_scheduler()
                close_device(self.id)

            def scheduler(self, callback, scheduler_type):
                if scheduler_type == "async":
                    hdAsyncSheduler(callback)
                else:
                    hdSyncSheduler(callback)

        hd_device.HapticDevice = HapticDevice
        package = types.ModuleType("pyOpenHaptics")
        package.__path__ = []
        package.hd, package.hd_device, package.hd_callback = hd, hd_device, hd_callback_mod
        return {"pyOpenHaptics": package, "pyOpenHaptics.hd": hd,
                "pyOpenHaptics.hd_device": hd_device,
                "pyOpenHaptics.hd_callback": hd_callback_mod}


@pytest.fixture
def touch(monkeypatch):
    fake = FakeTouch()
    install(monkeypatch, fake.modules())
    yield fake
    fake._stop.set()


def test_touch_units_axes_recentre_and_rotation(touch):
    touch.box_mm = [-80.0, -50.0, -40.0, 80.0, 70.0, 30.0]  # centre (0, 10, -5)
    touch.position_mm = [10.0, 20.0, 30.0]
    touch.velocity_mm_s = [1.0, 2.0, 3.0]
    touch.buttons = 0b10
    c, s = math.cos(0.3), math.sin(0.3)
    touch.rotation = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    with OpenHapticsDevice() as dev:
        assert dev.info.model == "Touch" and dev.info.limits is PROFILES["touch"]
        state = dev.cycle(np.array([1.0, 0.0, -1.0]))
        np.testing.assert_allclose(state.position_mm, [10.0, 10.0, 35.0])
        np.testing.assert_allclose(state.velocity_mm_s, [1.0, 2.0, 3.0])
        np.testing.assert_allclose(state.rotation, touch.rotation)
        assert state.buttons == 0b10
        assert wait_for(lambda: touch.force == [1.0, 0.0, -1.0])


def test_touch_explicit_centre(touch):
    touch.position_mm = [10.0, 20.0, 30.0]
    with OpenHapticsDevice(workspace_centre_mm=(10.0, 20.0, 30.0)) as dev:
        np.testing.assert_allclose(dev.cycle(np.zeros(3)).position_mm, np.zeros(3))


def test_touch_clamps_and_close_zeroes(touch):
    dev = OpenHapticsDevice()
    dev.open()
    dev.cycle(np.array([0.0, 10.0, 0.0]))
    assert wait_for(lambda: touch.force == [0.0, 3.3, 0.0])
    dev.cycle(np.array([1.0, 1.0, 0.0]))
    assert wait_for(lambda: touch.force == [1.0, 1.0, 0.0])
    dev.close()
    assert touch.force == [0.0, 0.0, 0.0]
    assert not touch.enabled and touch._thread is None
    with pytest.raises(DeviceError, match="not open"):
        dev.cycle(np.zeros(3))


def test_touch_servo_zeroes_a_stale_command(touch):
    with OpenHapticsDevice(stale_after_s=0.02) as dev:
        # Keep commanding until the servo callback has rendered the force once ...
        assert wait_for(lambda: dev.cycle(np.array([0.0, 0.0, 2.0])) is not None
                        and touch.force == [0.0, 0.0, 2.0])
        # ... then stop: with no further cycle the callback must drop the force by itself.
        assert wait_for(lambda: touch.force == [0.0, 0.0, 0.0])


def test_touch_scheduler_stall_is_a_disconnect(touch):
    with OpenHapticsDevice(scheduler_timeout_s=0.02) as dev:
        dev.cycle(np.zeros(3))
        touch.paused = True
        time.sleep(0.1)
        with pytest.raises(DeviceDisconnected, match="scheduler"):
            dev.cycle(np.zeros(3))
        touch.paused = False


def test_touch_init_failure_names_the_problem(monkeypatch):
    fake = FakeTouch(init_ok=False)
    install(monkeypatch, fake.modules())
    with pytest.raises(DeviceNotFound) as err:
        OpenHapticsDevice().open()
    assert "Unable to initialize" in str(err.value)
    assert 'ATTRS{idVendor}=="0301"' in str(err.value)
    assert fake._thread is None  # the scheduler it started was stopped


def test_touch_package_and_native_missing(monkeypatch, tmp_path):
    block(monkeypatch, "pyOpenHaptics", "pyOpenHaptics.hd")
    with pytest.raises(VendorLibraryMissing, match=r"pip install 'burrforce\[openhaptics\]'"):
        OpenHapticsDevice().open()
    # pyOpenHaptics loads libHD.so with ctypes at import: without OpenHaptics that is OSError.
    package = tmp_path / "pyOpenHaptics"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "hd.py").write_text(
        'raise OSError("libHD.so: cannot open shared object file: No such file or directory")\n')
    monkeypatch.delitem(sys.modules, "pyOpenHaptics")
    monkeypatch.delitem(sys.modules, "pyOpenHaptics.hd")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(VendorLibraryMissing, match=r"libHD\.so.*OpenHaptics"):
        OpenHapticsDevice().open()


# ---------------------------------------------------------------------------------------------
# HaplyHardwareAPI fake (0.1.13: detect_*, SerialStream, Inverse3, Handle)


class FakeInverse3:
    """A simulated Inverse3 in Haply's frame (m, m/s)."""

    def __init__(self, port: str, handle_port: str | None = None):
        self.port, self.handle_port = port, handle_port
        self.position_m = [0.0186, -0.153, 0.151]
        self.velocity_m_s = [0.0, 0.0, 0.0]
        self.forces: list[list[float]] = []
        self.silent = False  # nothing answers: the API logs and returns zeros
        self.broken = False  # the API raises
        self.handle_broken = False  # the VerseGrip's port cannot be opened
        self.streams: list[weakref.ref] = []  # every SerialStream made (the API closes the
        # port when its stream is destroyed)
        self.versegrip = {"device_id": 7, "quaternion": [1.0, 0.0, 0.0, 0.0],
                          "buttons": [False, False, False], "battery_level": 0.9}

    def module(self) -> types.ModuleType:
        dev = self
        api = types.ModuleType("HaplyHardwareAPI")

        def detect_inverse3s() -> list[str]:
            return [dev.port] if dev.port else []

        def detect_handles() -> list[str]:
            return [dev.handle_port] if dev.handle_port else []

        class SerialStream:
            def __init__(self, arg0: str):
                self.port = arg0
                dev.streams.append(weakref.ref(self))

        class UUID:
            def __init__(self, raw=(0,) * 16):
                self._raw = list(raw)

            def bytes(self) -> list[int]:
                return list(self._raw)

        class Inverse3:
            def __init__(self, stream, timeout: float = 5.0):
                self.stream = stream
                self.read_timeout = timeout

            def set_read_timeout(self, t: float) -> None:
                self.read_timeout = t

            def device_wakeup_dict(self) -> dict:
                if dev.silent:  # what HaplyHardwareAPI 0.1.13 returns after a timeout
                    return {"device_id": 21232, "device_model_number": 159,
                            "hardware_version": 86, "firmware_version": 255,
                            "device_id_ext": UUID()}
                return {"device_id": 4321, "device_model_number": 1, "hardware_version": 2,
                        "firmware_version": 3, "device_id_ext": UUID(range(1, 17))}

            def end_effector_force(self, forces=(0.0, 0.0, 0.0)) -> tuple:
                if dev.broken:
                    raise RuntimeError("serial port error")
                dev.forces.append(list(forces))
                if dev.silent:
                    return [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
                return list(dev.position_m), list(dev.velocity_m_s)

        class Handle:
            def __init__(self, arg0):
                if dev.handle_broken:
                    raise RuntimeError("could not open port")
                self.stream = arg0

            def GetVersegripStatus(self) -> dict:
                return dict(dev.versegrip)

        api.detect_inverse3s, api.detect_handles = detect_inverse3s, detect_handles
        api.SerialStream, api.Inverse3, api.Handle = SerialStream, Inverse3, Handle
        api.UUID = UUID
        return api


@pytest.fixture
def haply(monkeypatch, tmp_path):
    port = tmp_path / "ttyACM0"
    port.write_bytes(b"")
    fake = FakeInverse3(str(port), handle_port=str(port))
    monkeypatch.setitem(sys.modules, "HaplyHardwareAPI", fake.module())
    return fake


def test_haply_units_axes_and_info(haply):
    haply.position_m = [0.0186 + 0.010, -0.153 - 0.020, 0.151 + 0.030]
    haply.velocity_m_s = [0.1, 0.2, -0.3]
    with HaplyInverse3Device() as dev:
        state = dev.cycle(np.array([1.0, -2.0, 0.5]))
        np.testing.assert_allclose(state.position_mm, [10.0, -20.0, 30.0], atol=1e-9)
        np.testing.assert_allclose(state.velocity_mm_s, [100.0, 200.0, -300.0])
        assert haply.forces[-1] == [1.0, -2.0, 0.5]
        assert state.rotation is None and state.buttons == 0
        assert dev.info.serial == "4321" and dev.info.limits is INVERSE3_PROFILE
        assert dev.info.limits.name == "inverse3"


def test_haply_clamps_and_close_zeroes(haply):
    dev = HaplyInverse3Device()
    dev.open()
    dev.cycle(np.array([0.0, 0.0, -50.0]))
    assert haply.forces[-1] == [0.0, 0.0, -INVERSE3_PROFILE.max_force_N]
    dev.cycle(np.array([2.0, 0.0, 0.0]))
    dev.close()
    assert haply.forces[-1] == [0.0, 0.0, 0.0]
    with pytest.raises(DeviceError, match="not open"):
        dev.cycle(np.zeros(3))


def test_haply_versegrip_orientation_and_buttons(haply):
    half = math.sqrt(0.5)
    haply.versegrip["quaternion"] = [half, 0.0, 0.0, half]  # 90° about z
    haply.versegrip["buttons"] = [True, False, True]
    with HaplyInverse3Device(handle_port="auto") as dev:
        assert dev.info.sensed_rotation and dev.info.buttons == 3
        assert wait_for(lambda: dev.cycle(np.zeros(3)).rotation is not None)
        state = dev.cycle(np.zeros(3))
        np.testing.assert_allclose(state.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]],
                                   atol=1e-12)
        assert state.buttons == 0b101


def test_haply_silence_errors_and_gone(haply):
    with HaplyInverse3Device() as dev:
        haply.silent = True
        with pytest.raises(DeviceDisconnected, match="did not answer"):
            dev.cycle(np.zeros(3))
        haply.silent, haply.broken = False, True
        with pytest.raises(DeviceError, match="exchange failed: serial port error"):
            dev.cycle(np.zeros(3))
        os.unlink(haply.port)
        with pytest.raises(DeviceDisconnected, match="gone"):
            dev.cycle(np.zeros(3))
        haply.broken = False


def test_haply_not_found(haply):
    haply.silent = True
    with pytest.raises(DeviceNotFound, match="nothing answered"):
        HaplyInverse3Device().open()
    haply.port = ""
    with pytest.raises(DeviceNotFound, match="no Haply Inverse3"):
        HaplyInverse3Device().open()


def test_haply_versegrip_failure_releases_the_inverse3(haply):
    """An open that fails on its second part (the VerseGrip) releases the first (the
    Inverse3's port), instead of leaving it open until the process ends."""
    haply.handle_broken = True
    dev = HaplyInverse3Device(handle_port="auto")
    with pytest.raises(DeviceError, match="could not open the VerseGrip"):
        dev.open()
    assert not dev.is_open
    gc.collect()
    assert haply.streams and all(ref() is None for ref in haply.streams)
    haply.handle_broken = False
    with HaplyInverse3Device(handle_port="auto") as again:
        assert again.cycle(np.zeros(3)).position_mm is not None


def test_haply_real_api_on_a_silent_port():
    """HaplyHardwareAPI itself (when installed) on a pseudo-terminal where nothing answers:
    open must fail clearly, not return the API's made-up wake-up reply."""
    pytest.importorskip("HaplyHardwareAPI")
    import pty
    import tty

    controller, port = pty.openpty()
    tty.setraw(port)
    try:
        with pytest.raises(DeviceNotFound, match="nothing answered"):
            HaplyInverse3Device(port=os.ttyname(port)).open()
    finally:
        os.close(controller)
        os.close(port)


def test_haply_package_missing(monkeypatch):
    block(monkeypatch, "HaplyHardwareAPI")
    with pytest.raises(VendorLibraryMissing, match=r"pip install 'burrforce\[haply\]'"):
        HaplyInverse3Device().open()


@given(st.lists(st.floats(-10, 10), min_size=4, max_size=4).filter(
    lambda q: sum(v * v for v in q) > 1e-6))
def test_quaternion_gives_a_rotation(q):
    r = quaternion_to_rotation(q)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-9)
    assert math.isclose(np.linalg.det(r), 1.0, abs_tol=1e-9)


def test_buttons_mask_forms():
    assert buttons_mask(5) == 5 and buttons_mask(True) == 1
    assert buttons_mask([False, True]) == 2
    assert buttons_mask({"a": True, "b": False, "c": True}) == 0b101
    assert buttons_mask(None) == 0


# ---------------------------------------------------------------------------------------------
# every back-end: the last line of defence clamps any force to the profile's maximum


@given(st.lists(st.floats(-1e6, 1e6), min_size=3, max_size=3))
def test_fd_never_exceeds_max_force(force):
    fake = FakeFD()
    saved = {k: sys.modules.get(k) for k in fake.modules()}
    sys.modules.update(fake.modules())
    try:
        with ForceDimensionDevice() as dev:
            dev.cycle(np.array(force))
            applied = np.array(fake.force)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    assert np.linalg.norm(applied) <= PROFILES["omega3"].max_force_N * (1 + 1e-12)
    wanted = np.array(force)
    if np.linalg.norm(wanted) > 1e-9:
        # Same direction: scaling never rotates the force.
        assert np.linalg.norm(np.cross(applied, wanted)) <= 1e-6 * np.linalg.norm(wanted)
