"""What this machine can drive: every back-end, whether its requirements are installed, and the
units plugged in (``burrforce devices``, ``--json`` prints :func:`list_devices` as is).

Detection without side effects: USB devices are listed through libusb's descriptors (pyusb;
libusb from ``libusb-package``, else the system's) and matched against the known identities
(``devices.udev``); nothing is opened or claimed. Whether this user may open a unit is
``os.access`` on its device node (``/dev/bus/usb/BBB/DDD``, or the ``/dev/ttyACM*`` the
kernel made of a USB serial device, found through sysfs); when it may not, the unit carries the
udev rule that fixes it. Vendor packages are looked up, not imported (importing them loads
their native libraries); their native libraries are searched where the vendors' wrappers look.
Sound cards are listed through PortAudio (sounddevice), which is loaded for that.

Everything returned is JSON-serialisable. A missing library is reported, never raised.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import glob
import importlib
import importlib.util
import os
import platform
import re
from collections.abc import Iterable
from dataclasses import dataclass, field

from .registry import ACTUATORS, HAPTIC
from .udev import RELOAD_COMMANDS, RULES_PATH, UsbIdentity, known_identities, match, rule
from .usb import find_libusb

#: Where device nodes and USB sysfs entries live (tests under umockdev see its testbed here).
DEV_ROOT = "/dev"
SYSFS_USB = "/sys/bus/usb/devices"

#: Python modules each back-end imports: (import name, what to pip install).
PYTHON_NEEDS: dict[str, tuple[tuple[str, str], ...]] = {
    "sim": (("numpy", "numpy"),),
    "falcon": (("usb", "pyusb"),),
    "forcedimension": (("forcedimension_core", "burrforce[forcedimension]"),),
    "openhaptics": (("pyOpenHaptics", "burrforce[openhaptics]"),),
    "haply": (("HaplyHardwareAPI", "burrforce[haply]"),),
    "audio": (("sounddevice", "sounddevice"),),
    "usb": (("usb", "pyusb"),),
    "wav": (),
}
#: Back-ends that talk to USB through libusb.
LIBUSB_BACKENDS = ("falcon", "usb")
#: Back-ends without hardware.
VIRTUAL_BACKENDS = ("sim", "wav")
_HAPLY_SERIAL_NAME = re.compile(r"haply|inverse", re.IGNORECASE)


# -- requirements -------------------------------------------------------------------------


def _requirement(name: str, ok: bool, detail: str, kind: str = "python") -> dict:
    return {"name": name, "kind": kind, "ok": ok, "detail": detail}


def _python_requirement(module: str, pip_name: str) -> dict:
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        found = False
    return _requirement(pip_name, found, f"module {module!r} " + (
        "found" if found else f"missing: pip install '{pip_name}'"))


def find_libdrd() -> str | None:
    """The Force Dimension SDK's libdrd where forcedimension-core looks for it (``$FDSDK`` or
    ``$FORCEDIM_SDK``/lib/release/lin-<arch>-gcc, ``~/.local/lib``, ``/usr/local/lib``)."""
    folders = [os.path.join(os.environ[var], "lib", "release",
                            f"lin-{platform.machine()}-gcc")
               for var in ("FDSDK", "FORCEDIM_SDK") if os.environ.get(var)]
    folders += [os.path.expanduser("~/.local/lib"), "/usr/local/lib"]
    for folder in folders:
        hits = sorted(glob.glob(os.path.join(folder, "libdrd.so*")))
        if hits:
            return hits[-1]
    return None


def find_libhd() -> str | None:
    """OpenHaptics' libHD.so as ``ctypes.CDLL("libHD.so")`` would find it (loader path or
    ``LD_LIBRARY_PATH``), without loading it."""
    for folder in filter(None, os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep)):
        path = os.path.join(folder, "libHD.so")
        if os.path.exists(path):
            return path
    return ctypes.util.find_library("HD")


def _native_requirements(name: str, usb: UsbScan | None) -> list[dict]:
    if name in LIBUSB_BACKENDS:
        if usb is None:
            return []
        return [_requirement("libusb-1.0", usb.libusb is not None,
                             usb.libusb or usb.error or "", kind="native")]
    if name == "forcedimension":
        path = find_libdrd()
        return [_requirement("Force Dimension SDK (libdrd)", path is not None,
                             path or "not found: install the Force Dimension SDK and set "
                             "FDSDK to its folder", kind="native")]
    if name == "openhaptics":
        path = find_libhd()
        return [_requirement("OpenHaptics (libHD.so)", path is not None,
                             path or "not found: install OpenHaptics and the Touch device "
                             "driver; make libHD.so loadable (ldconfig or LD_LIBRARY_PATH)",
                             kind="native")]
    return []


# -- USB ----------------------------------------------------------------------------------


@dataclass
class UsbScan:
    """What libusb sees. Attributes: libusb: which libusb was used (None: none);
    error: why the scan did not run or failed; devices: (vid, pid, bus, address, port
    numbers) of every device."""

    libusb: str | None = None
    error: str | None = None
    devices: list[tuple[int, int, int, int, tuple[int, ...]]] = field(default_factory=list)


def scan_usb() -> UsbScan:
    """List the USB devices libusb sees (descriptors only: nothing is opened)."""
    backend, description = find_libusb()
    if backend is None:
        return UsbScan(error=description)
    import usb.core

    scan = UsbScan(libusb=description)
    try:
        for dev in usb.core.find(find_all=True, backend=backend):
            ports: tuple[int, ...] = ()
            with contextlib.suppress(Exception):  # not every platform/backend knows them
                ports = tuple(dev.port_numbers or ())
            scan.devices.append((int(dev.idVendor), int(dev.idProduct), int(dev.bus or 0),
                                 int(dev.address or 0), ports))
    except Exception as exc:  # usb.core.USBError, NoBackendError: report, do not crash
        scan.error = f"USB scan failed: {exc}"
    return scan


def _tty_nodes(bus: int, ports: tuple[int, ...]) -> list[str]:
    """The serial ports (``/dev/ttyACM0`` ...) the kernel made of a USB device."""
    if not ports:
        return []
    device = os.path.join(SYSFS_USB, f"{bus}-{'.'.join(str(p) for p in ports)}")
    names = {os.path.basename(p) for pattern in ("*/tty/*", "*/tty*/tty/*")
             for p in glob.glob(os.path.join(device, pattern))}
    return [os.path.join(DEV_ROOT, n) for n in sorted(names)]


def _access(node: str) -> tuple[bool, str | None]:
    if not os.path.exists(node):
        return False, f"no device node {node}"
    if os.access(node, os.R_OK | os.W_OK):
        return True, None
    return False, f"this user may not open {node}"


def _unit(identity: UsbIdentity, vid: int, pid: int, bus: int, address: int,
          ports: tuple[int, ...]) -> dict:
    usb_node = os.path.join(DEV_ROOT, "bus", "usb", f"{bus:03d}", f"{address:03d}")
    ttys = _tty_nodes(bus, ports)
    if identity.node == "tty":
        node = ttys[0] if ttys else None
        accessible, problem = _access(node) if node else (
            False, "no serial port for it (is the cdc_acm kernel module loaded?)")
    else:
        node = usb_node
        accessible, problem = _access(node)
    unit = {"backend": identity.backend, "label": identity.label,
            "vid": f"{vid:04x}", "pid": f"{pid:04x}", "bus": bus, "address": address,
            "candidate": identity.candidate, "node": node, "usb_node": usb_node,
            "serial_ports": ttys, "accessible": accessible, "problem": problem,
            "udev_rule": None, "rules_path": None, "reload_commands": None}
    if not accessible and node is not None and os.path.exists(node):
        unit.update(udev_rule=rule(identity), rules_path=RULES_PATH,
                    reload_commands=list(RELOAD_COMMANDS))
    return unit


def _usb_units(scan: UsbScan) -> dict[str, list[dict]]:
    units: dict[str, list[dict]] = {}
    for vid, pid, bus, address, ports in scan.devices:
        for identity in match(vid, pid):
            units.setdefault(identity.backend, []).append(
                _unit(identity, vid, pid, bus, address, ports))
    return units


def _haply_serial_units(known_nodes: Iterable[str]) -> list[dict]:
    """Inverse3 ports named by udev's ``/dev/serial/by-id`` links that the USB scan missed."""
    seen = {os.path.realpath(n) for n in known_nodes if n}
    units = []
    for link in sorted(glob.glob(os.path.join(DEV_ROOT, "serial", "by-id", "*"))):
        node = os.path.realpath(link)
        if not _HAPLY_SERIAL_NAME.search(os.path.basename(link)) or node in seen:
            continue
        accessible, problem = _access(node)
        identity = next((i for i in known_identities() if i.backend == "haply"), None)
        units.append({"backend": "haply", "label": "Haply device", "by_id": link,
                      "node": node, "candidate": False, "accessible": accessible,
                      "problem": problem,
                      "udev_rule": None if accessible or identity is None else rule(identity),
                      "rules_path": None if accessible else RULES_PATH,
                      "reload_commands": None if accessible else list(RELOAD_COMMANDS)})
        seen.add(node)
    return units


# -- audio --------------------------------------------------------------------------------


def _audio() -> tuple[list[dict], list[dict]]:
    """(native requirements, output devices) through sounddevice/PortAudio."""
    try:
        sd = importlib.import_module("sounddevice")
    except ImportError:
        return [], []  # the Python requirement already says so
    except OSError as exc:  # sounddevice loads PortAudio at import
        return [_requirement("PortAudio", False, f"{exc}: apt-get install libportaudio2",
                             kind="native")], []
    need = [_requirement("PortAudio", True, str(sd.get_portaudio_version()[1]), kind="native")]
    try:
        devices = sd.query_devices()
        hostapis = sd.query_hostapis()
        default_out = sd.default.device[1]
    except Exception as exc:  # PortAudioError: report, do not crash
        need.append(_requirement("sound devices", False, f"PortAudio failed: {exc}",
                                 kind="native"))
        return need, []
    units = [{"backend": "audio", "index": i, "name": str(d["name"]),
              "hostapi": str(hostapis[d["hostapi"]]["name"]),
              "channels": int(d["max_output_channels"]),
              "default_samplerate_hz": float(d["default_samplerate"]),
              "default": i == default_out, "accessible": True}
             for i, d in enumerate(devices) if d["max_output_channels"] > 0]
    return need, units


# -- the listing ----------------------------------------------------------------------------


def list_devices(*, usb: bool = True, audio: bool = True) -> list[dict]:
    """Every supported back-end, haptic devices first. Each entry: ``name``, ``kind``
    (``haptic``/``actuator``), ``summary``, ``needs`` (what it needs beyond burrforce),
    ``virtual`` (no hardware), ``requirements`` (each ``{name, kind, ok, detail}``),
    ``ready`` (all requirements met), ``units`` (detected hardware, each with ``accessible``
    and, when it is there but not accessible, ``udev_rule``, ``rules_path`` and
    ``reload_commands``). ``usb``/``audio`` False skip those scans (their units stay empty)."""
    scan = scan_usb() if usb else None
    units = _usb_units(scan) if scan is not None else {}
    if usb:
        units.setdefault("haply", []).extend(_haply_serial_units(
            u["node"] for u in units.get("haply", [])))
    audio_needs, audio_units = _audio() if audio else ([], [])
    entries = []
    for backend in (*HAPTIC.values(), *ACTUATORS.values()):
        needs = [_python_requirement(m, pip) for m, pip in PYTHON_NEEDS.get(backend.name, ())]
        needs += _native_requirements(backend.name, scan)
        found = list(units.get(backend.name, ()))
        if backend.name == "audio":
            needs += audio_needs
            found = audio_units
        entries.append({
            "name": backend.name, "kind": backend.kind, "summary": backend.summary,
            "needs": backend.needs, "virtual": backend.name in VIRTUAL_BACKENDS,
            "requirements": needs, "ready": all(n["ok"] for n in needs), "units": found})
    return entries


def format_devices(entries: list[dict]) -> str:
    """:func:`list_devices` for people: one block per back-end."""
    lines = []
    for e in entries:
        state = "ready" if e["ready"] else "not ready"
        lines.append(f"{e['name']} ({e['kind']}, {state}): {e['summary']}")
        for need in e["requirements"]:
            if not need["ok"]:
                lines.append(f"    missing {need['name']}: {need['detail']}")
        for u in e["units"]:
            if e["name"] == "audio":
                mark = " (default)" if u["default"] else ""
                lines.append(f"    [{u['index']}] {u['name']} — {u['hostapi']}, "
                             f"{u['channels']} ch{mark}")
                continue
            where = u.get("node") or "?"
            ids = f" {u['vid']}:{u['pid']}" if "vid" in u else ""
            guess = " (candidate)" if u.get("candidate") else ""
            access = "accessible" if u["accessible"] else f"NOT accessible: {u['problem']}"
            lines.append(f"    {u['label']}{ids}{guess} at {where}: {access}")
            if u.get("udev_rule"):
                lines.append(f"      add to {u['rules_path']}:\n        {u['udev_rule']}")
                lines += [f"      then run: {cmd}" for cmd in u["reload_commands"]]
        if not e["units"] and not e["virtual"]:
            lines.append("    no unit detected")
    return "\n".join(lines)
