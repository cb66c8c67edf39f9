"""Device discovery and udev rules: on this machine (no USB devices, maybe no /dev/bus/usb),
with a made-up /dev and sysfs tree for the node and serial-port logic, and — when the
umockdev emulation of a device is available — end to end against the emulated device in a
preloaded subprocess."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import subprocess
import sys

import pytest

from burrforce.server.devices import discovery, udev
from burrforce.server.devices.registry import ACTUATORS, HAPTIC

EXPECTED = {"sim": "haptic", "falcon": "haptic", "forcedimension": "haptic",
            "openhaptics": "haptic", "haply": "haptic",
            "audio": "actuator", "usb": "actuator", "wav": "actuator"}


def by_name(entries):
    return {e["name"]: e for e in entries}


# -- this machine ---------------------------------------------------------------------------


def test_lists_every_backend_without_raising_and_is_json():
    entries = discovery.list_devices()
    assert {e["name"]: e["kind"] for e in entries} == EXPECTED
    assert [e["name"] for e in entries] == [*HAPTIC, *ACTUATORS]
    json.loads(json.dumps(entries))  # plain JSON types only
    for e in entries:
        assert isinstance(e["ready"], bool) and isinstance(e["units"], list)
        assert e["ready"] == all(r["ok"] for r in e["requirements"])
    assert by_name(entries)["sim"]["virtual"] and by_name(entries)["wav"]["virtual"]
    assert discovery.format_devices(entries).startswith("sim (haptic")


@pytest.mark.skipif(os.path.isdir("/dev/bus/usb") and os.listdir("/dev/bus/usb"),
                    reason="this machine has USB devices (allowed in CI)")
def test_no_usb_hardware_means_no_units():
    entries = by_name(discovery.list_devices(audio=False))
    for name in ("sim", "falcon", "forcedimension", "openhaptics", "haply", "usb", "wav"):
        assert entries[name]["units"] == [], name
    falcon_needs = {r["name"]: r for r in entries["falcon"]["requirements"]}
    assert falcon_needs["pyusb"]["ok"] and falcon_needs["libusb-1.0"]["ok"]


def test_vendor_packages_are_reported_not_imported(monkeypatch):
    monkeypatch.delenv("FDSDK", raising=False)
    monkeypatch.delenv("FORCEDIM_SDK", raising=False)
    entries = by_name(discovery.list_devices(usb=False, audio=False))
    fd = {r["name"]: r for r in entries["forcedimension"]["requirements"]}
    if importlib.util.find_spec("forcedimension_core") is None:
        assert not fd["burrforce[forcedimension]"]["ok"]
        assert "pip install 'burrforce[forcedimension]'" in fd["burrforce[forcedimension]"][
            "detail"]
        assert "forcedimension_core" not in sys.modules
    if discovery.find_libdrd() is None:
        assert "FDSDK" in fd["Force Dimension SDK (libdrd)"]["detail"]
        assert not entries["forcedimension"]["ready"]


def test_libdrd_is_found_where_forcedimension_core_looks(monkeypatch, tmp_path):
    import platform

    folder = tmp_path / "lib" / "release" / f"lin-{platform.machine()}-gcc"
    folder.mkdir(parents=True)
    (folder / "libdrd.so.3.17.6").write_bytes(b"")
    monkeypatch.setenv("FDSDK", str(tmp_path))
    assert discovery.find_libdrd() == str(folder / "libdrd.so.3.17.6")


def test_no_libusb_is_reported_not_raised(monkeypatch):
    import usb.backend.libusb1

    monkeypatch.setitem(sys.modules, "libusb_package", None)
    monkeypatch.setattr(usb.backend.libusb1, "get_backend", lambda *a, **k: None)
    entries = by_name(discovery.list_devices(audio=False))
    libusb = {r["name"]: r for r in entries["falcon"]["requirements"]}["libusb-1.0"]
    assert not libusb["ok"] and "apt-get install libusb-1.0-0" in libusb["detail"]
    assert entries["falcon"]["units"] == [] and not entries["usb"]["ready"]


def test_no_pyusb_is_reported_not_raised(monkeypatch):
    for name in ("usb", "usb.core", "usb.backend", "usb.backend.libusb1"):
        monkeypatch.setitem(sys.modules, name, None)
    entries = by_name(discovery.list_devices(audio=False))
    needs = {r["name"]: r for r in entries["falcon"]["requirements"]}
    assert not needs["pyusb"]["ok"] and "pip install 'pyusb'" in needs["pyusb"]["detail"]
    assert "pip install pyusb" in needs["libusb-1.0"]["detail"]


def test_missing_portaudio_names_the_debian_package(monkeypatch, tmp_path):
    # sounddevice raises OSError at import when PortAudio cannot be loaded.
    (tmp_path / "sounddevice.py").write_text('raise OSError("PortAudio library not found")\n')
    monkeypatch.delitem(sys.modules, "sounddevice", raising=False)
    monkeypatch.syspath_prepend(str(tmp_path))
    audio = by_name(discovery.list_devices(usb=False))["audio"]
    portaudio = {r["name"]: r for r in audio["requirements"]}["PortAudio"]
    assert not portaudio["ok"] and "apt-get install libportaudio2" in portaudio["detail"]
    assert audio["units"] == [] and not audio["ready"]


# -- nodes, serial ports, access (a made-up /dev and sysfs) -------------------------------


@pytest.fixture
def fake_roots(monkeypatch, tmp_path):
    dev, sysfs = tmp_path / "dev", tmp_path / "sys"
    dev.mkdir()
    sysfs.mkdir()
    monkeypatch.setattr(discovery, "DEV_ROOT", str(dev))
    monkeypatch.setattr(discovery, "SYSFS_USB", str(sysfs))
    return dev, sysfs


def deny(monkeypatch, path):
    """This user may not open ``path`` (root passes every os.access check, so the kernel's
    answer is stood in for)."""
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if os.fspath(p) == str(path)
                        else real(p, mode, **kw))


def test_usb_unit_accessible_and_denied(fake_roots, monkeypatch):
    dev, _ = fake_roots
    node = dev / "bus" / "usb" / "001" / "005"
    node.parent.mkdir(parents=True)
    node.write_bytes(b"")
    scan = discovery.UsbScan(libusb="test", devices=[(0x0403, 0xCB48, 1, 5, (2,)),
                                                     (0x1D6B, 0x0002, 1, 1, ())])
    (unit,) = discovery._usb_units(scan)["falcon"]
    assert unit["node"] == str(node) and unit["accessible"] and unit["udev_rule"] is None
    assert (unit["vid"], unit["pid"], unit["bus"], unit["address"]) == ("0403", "cb48", 1, 5)
    deny(monkeypatch, node)
    (unit,) = discovery._usb_units(scan)["falcon"]
    assert not unit["accessible"] and "may not open" in unit["problem"]
    assert unit["udev_rule"] == udev.rule(udev.identities_for("falcon")[0])
    assert unit["rules_path"] == "/etc/udev/rules.d/70-burrforce.rules"
    assert unit["reload_commands"] == ["sudo udevadm control --reload-rules",
                                       "sudo udevadm trigger"]
    json.dumps(unit)


def test_missing_node_is_a_problem_without_a_rule(fake_roots):
    scan = discovery.UsbScan(libusb="test", devices=[(0x1451, 0x0402, 3, 7, (1, 4))])
    (unit,) = discovery._usb_units(scan)["forcedimension"]
    assert not unit["accessible"] and "no device node" in unit["problem"]
    assert unit["udev_rule"] is None


def test_touch_is_found_by_its_serial_port(fake_roots, monkeypatch):
    dev, sysfs = fake_roots
    (sysfs / "1-2.3" / "1-2.3:1.0" / "tty" / "ttyACM0").mkdir(parents=True)
    (dev / "ttyACM0").write_bytes(b"")
    scan = discovery.UsbScan(libusb="test", devices=[(0x0301, 0x2988, 1, 9, (2, 3))])
    (unit,) = discovery._usb_units(scan)["openhaptics"]
    assert unit["node"] == str(dev / "ttyACM0") and unit["accessible"]
    assert unit["serial_ports"] == [str(dev / "ttyACM0")]
    deny(monkeypatch, dev / "ttyACM0")
    (unit,) = discovery._usb_units(scan)["openhaptics"]
    assert unit["udev_rule"].startswith('SUBSYSTEM=="tty", ATTRS{idVendor}=="0301", '
                                        'ATTRS{idProduct}=="2988"')


def test_serial_device_without_port_says_why(fake_roots):
    scan = discovery.UsbScan(libusb="test", devices=[(0x2FE3, 0x0100, 1, 3, (1,))])
    (unit,) = discovery._usb_units(scan)["haply"]
    assert unit["candidate"] and unit["node"] is None and "cdc_acm" in unit["problem"]


def test_haply_by_id_link(fake_roots):
    dev, _ = fake_roots
    (dev / "ttyACM1").write_bytes(b"")
    (dev / "serial" / "by-id").mkdir(parents=True)
    (dev / "serial" / "by-id" / "usb-Haply_Robotics_Inverse3_1234-if00").symlink_to(
        dev / "ttyACM1")
    (dev / "serial" / "by-id" / "usb-Some_Other_Thing-if00").symlink_to(dev / "ttyACM1")
    (unit,) = discovery._haply_serial_units([])
    assert unit["node"] == str(dev / "ttyACM1") and unit["accessible"]
    assert discovery._haply_serial_units([str(dev / "ttyACM1")]) == []


# -- udev rules -----------------------------------------------------------------------------

RULE = re.compile(r'^(?:[A-Z]+(?:\{\w+\})?(?:==|\+?=)"[^"]*"(?:, |$))+$')


def test_rule_texts():
    falcon = udev.identities_for("falcon")[0]
    assert udev.rule(falcon) == (
        'SUBSYSTEM=="usb", ENV{DEVTYPE}=="usb_device", ATTR{idVendor}=="0403", '
        'ATTR{idProduct}=="cb48", MODE="0660", GROUP="plugdev", TAG+="uaccess"')
    fd = udev.identities_for("forcedimension")[0]
    assert 'ATTR{idVendor}=="1451"' in udev.rule(fd) and "idProduct" not in udev.rule(fd)
    assert fd.ids == "1451:*" and falcon.ids == "0403:cb48"
    board = udev.identities_for("usb")
    assert board and board[0].ids == "1209:0001"
    for identity in udev.known_identities():
        assert RULE.match(udev.rule(identity)), udev.rule(identity)


def test_rules_file_and_help():
    text = udev.rules_file()
    assert text.endswith("\n")
    rules = [line for line in text.splitlines() if line and not line.startswith("#")]
    assert rules == [udev.rule(i) for i in udev.known_identities()]
    assert udev.RULES_PATH in text and all(cmd in text for cmd in udev.RELOAD_COMMANDS)
    help_text = udev.access_help(udev.identities_for("falcon")[0])
    assert udev.RULES_PATH in help_text and udev.rule(udev.identities_for("falcon")[0]) \
        in help_text
    assert all(cmd in help_text for cmd in udev.RELOAD_COMMANDS)
    assert udev.backend_access_help("sim") == ""


def test_identity_validation_and_matching():
    with pytest.raises(ValueError, match="node"):
        udev.UsbIdentity("x", "x", 1, 2, node="hid")
    with pytest.raises(ValueError, match="16-bit"):
        udev.UsbIdentity("x", "x", 0x10000, None)
    assert [i.backend for i in udev.match(0x1451, 0x1234)] == ["forcedimension"]
    assert udev.match(0x0403, 0x6001) == ()  # a plain FTDI cable is not a Falcon


# -- end to end under umockdev ----------------------------------------------------------------

DISCOVER = ("import json; from burrforce.server.devices.discovery import list_devices; "
            "print(json.dumps(list_devices(audio=False)))")


@pytest.mark.parametrize(("kind", "backend", "options"), [
    ("falcon", "falcon", {"firmware_loaded": True}),
    ("board", "usb", {}),
])
def test_discovery_sees_an_emulated_device(kind, backend, options):
    from support.emulation.launcher import (
        EmulatedUsb,
        emulation_unavailable_reason,
    )

    reason = emulation_unavailable_reason()
    if reason:
        pytest.skip(f"umockdev emulation unavailable: {reason}")
    if importlib.util.find_spec(f"support.emulation.{kind}") is None:
        pytest.skip(f"no emulated {kind} (support.emulation.{kind})")
    with EmulatedUsb(kind, bus=1, devnum=4, **options) as emu:
        run = subprocess.run([sys.executable, "-c", DISCOVER], env=emu.client_env(),
                             capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    entries = by_name(json.loads(run.stdout))
    (unit,) = entries[backend]["units"]
    assert (unit["bus"], unit["address"]) == (1, 4)
    assert unit["node"] == "/dev/bus/usb/001/004" and unit["accessible"]
    others = [n for n, e in entries.items() if e["units"] and n != backend]
    assert others == []


def test_scan_sees_the_emulated_loopback_device():
    from support.emulation.launcher import (
        EmulatedUsb,
        emulation_unavailable_reason,
    )

    reason = emulation_unavailable_reason()
    if reason:
        pytest.skip(f"umockdev emulation unavailable: {reason}")
    code = ("import json; from burrforce.server.devices.discovery import scan_usb; "
            "s = scan_usb(); print(json.dumps([s.libusb, s.error, s.devices]))")
    with EmulatedUsb("loopback", bus=1, devnum=3) as emu:
        run = subprocess.run([sys.executable, "-c", code], env=emu.client_env(),
                             capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    libusb, error, devices = json.loads(run.stdout)
    assert libusb and error is None
    assert [0x1209, 0x0002, 1, 3, [1]] in devices
