"""The Falcon back-end without a Falcon: firmware image checks, USB error mapping, device
discovery through the real libusb. The I/O path runs against the umockdev emulation in
``test_falcon_emulated.py``."""

from __future__ import annotations

import errno
import hashlib
import logging

import pytest
import usb.core

from burrforce.server.devices.base import (
    DeviceAccessDenied,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
)
from burrforce.server.devices.falcon import FalconDevice
from burrforce.server.devices.falcon import firmware as FW
from burrforce.server.devices.falcon import protocol as P
from burrforce.server.devices.falcon.device import default_backend
from burrforce.server.devices.falcon.ftdi import map_usb_error
from burrforce.server.haptics.profiles import PROFILES


def test_firmware_image_is_read_and_identified(tmp_path, caplog):
    data = bytes(range(256)) * 33  # 8448 B, not a Novint image
    path = tmp_path / "fw.bin"
    path.write_bytes(data)
    with caplog.at_level(logging.WARNING):
        image = FW.read_firmware_image(path)
    assert image.data == data
    assert image.sha256 == hashlib.sha256(data).hexdigest()
    assert image.known_as is None
    assert "not one of the images" in caplog.text
    assert image.sha256[:16] in image.describe()


def test_firmware_image_matching_a_known_digest_is_named(tmp_path, monkeypatch):
    data = b"\xaa\x08" + bytes(5000)
    path = tmp_path / "nvent.bin"
    path.write_bytes(data)
    monkeypatch.setitem(FW.KNOWN_FIRMWARE_SHA256, hashlib.sha256(data).hexdigest(), "nvent")
    assert FW.read_firmware_image(path).known_as == "nvent"


@pytest.mark.parametrize("size", [0, FW.MIN_FIRMWARE_BYTES - 1, FW.MAX_FIRMWARE_BYTES + 1])
def test_firmware_image_of_implausible_size_is_refused(tmp_path, size):
    path = tmp_path / "fw.bin"
    path.write_bytes(bytes(size))
    with pytest.raises(FW.FirmwareError, match=f"{size} bytes"):
        FW.read_firmware_image(path)


def test_missing_firmware_image_is_a_clear_error(tmp_path):
    with pytest.raises(FW.FirmwareError, match="does not exist"):
        FW.read_firmware_image(tmp_path / "nope.bin")
    with pytest.raises(FW.FirmwareError, match="does not exist"):
        FW.read_firmware_image(tmp_path)  # a directory
    with pytest.raises(FW.FirmwareError, match="does not exist"):
        FalconDevice(firmware=str(tmp_path / "nope.bin"))


def test_no_firmware_help_says_where_to_get_it():
    assert "nvent_firmware.bin" in FW.NO_FIRMWARE_HELP
    assert "libnifalcon" in FW.NO_FIRMWARE_HELP
    assert "firmware=" in FW.NO_FIRMWARE_HELP
    assert issubclass(FW.FirmwareError, DeviceError)


@pytest.mark.parametrize("bad", [-1, 1.0, "0", True, None])
def test_index_must_be_a_natural_number(bad):
    with pytest.raises(ValueError, match="index"):
        FalconDevice(index=bad)


def test_info_uses_the_falcon_profile():
    info = FalconDevice().info
    assert info.backend == "falcon" and info.model == "Novint Falcon"
    assert info.limits is PROFILES["falcon"]
    assert info.workspace_radius_mm == pytest.approx(40.0)
    assert info.servo_rate_hz == 1000.0 and info.buttons == 4 and not info.sensed_rotation


def _usb_error(err: int | None, code: int | None = None) -> usb.core.USBError:
    return usb.core.USBError("boom", error_code=code, errno=err)


@pytest.mark.parametrize("err", [errno.ENODEV, errno.EIO, errno.ENOENT, errno.EPIPE])
def test_gone_errors_map_to_disconnected(err):
    mapped = map_usb_error(_usb_error(err), "reading")
    assert type(mapped) is DeviceDisconnected
    assert "reading" in str(mapped)


@pytest.mark.parametrize("code", [-1, -4, -5, -9])
def test_libusb_codes_without_errno_map_too(code):
    assert type(map_usb_error(_usb_error(None, code), "x")) is DeviceDisconnected


@pytest.mark.parametrize("exc", [_usb_error(errno.EACCES), _usb_error(errno.EPERM),
                                 _usb_error(None, -3)])
def test_access_errors_say_which_udev_rule_to_add(exc):
    mapped = map_usb_error(exc, "opening")
    assert type(mapped) is DeviceAccessDenied
    text = str(mapped).lower()
    assert "0403" in text and "cb48" in text and "plugdev" in text


def test_other_errors_stay_device_errors():
    busy = map_usb_error(_usb_error(errno.EBUSY), "claiming")
    assert type(busy) is DeviceError and "another program" in str(busy)
    timeout = map_usb_error(_usb_error(errno.ETIMEDOUT), "reading")
    assert type(timeout) is DeviceError and "in time" in str(timeout)
    assert type(map_usb_error(_usb_error(errno.EINVAL), "x")) is DeviceError
    already = DeviceDisconnected("gone")
    assert map_usb_error(already, "x") is already


def test_open_without_a_falcon_raises_not_found():
    backend = default_backend()
    if usb.core.find(idVendor=P.VID, idProduct=P.PID, backend=backend) is not None:
        pytest.skip("a Novint Falcon is plugged in (allowed in CI)")
    dev = FalconDevice(backend=backend)
    with pytest.raises(DeviceNotFound, match="0403:cb48"):
        dev.open()
    assert not dev.is_open
    dev.close()  # harmless on a device that never opened


def test_cycle_and_home_need_an_open_device():
    dev = FalconDevice()
    with pytest.raises(DeviceError, match="not open"):
        dev.cycle([0.0, 0.0, 0.0])
    with pytest.raises(DeviceError, match="open"):
        dev.home(timeout_s=0.1)
