"""The USB identities burrforce drives, and the Linux udev rules that let a user open them.

On Linux a USB device node (``/dev/bus/usb/BBB/DDD``) or a USB serial port (``/dev/ttyACM*``)
is root's unless a udev rule says otherwise. One rules file covers every device burrforce
knows; its ``70-`` prefix matters: ``TAG+="uaccess"`` (access for the user logged in at the
machine's seat) is only honoured by rules that run before systemd's ``73-seat-late.rules``.
Users on a machine without a local seat (SSH, a container host) join the ``plugdev`` group.

Sources of the identities (the ids of the devices burrforce drives itself are in
``devices.usb_ids``): Novint Falcon, libnifalcon; Force
Dimension, USB vendor id 0x1451 for all its devices (Force Dimension's udev rules as quoted
by SDK users; the forcedimension-core wheel holds no USB ids); 3D Systems Touch, a CDC-ACM
serial device 0301:2988 (jhu-saw/sawSensablePhantom); Haply Inverse3, vendor ids 0x2FE3 and
0x16C0 as listed in the device detection of the HaplyHardwareAPI 0.1.13 wheel (not checked
on hardware; 0x16C0 is a shared vendor id, so a match there is a candidate only); the
burrforce vibration board (``devices.actuators.board_protocol``).
"""

from __future__ import annotations

from dataclasses import dataclass

from .usb_ids import BOARD_PID, BOARD_VID, FALCON_PID, FALCON_VID

#: Where the rules go, and the two commands that make udev apply them (then replug).
RULES_PATH = "/etc/udev/rules.d/70-burrforce.rules"
RELOAD_COMMANDS = ("sudo udevadm control --reload-rules", "sudo udevadm trigger")
#: The group the rules grant access to (Debian/Ubuntu convention).
GROUP = "plugdev"


@dataclass(frozen=True)
class UsbIdentity:
    """A USB device a back-end drives.

    Attributes:
        backend: the back-end's name (``falcon``, ``forcedimension``, ``usb``, ...).
        label: what a user calls the device.
        vid: USB vendor id.
        pid: USB product id, or None for every product of ``vid``.
        node: which device node the back-end opens: ``usb`` (``/dev/bus/usb/...``, through
            libusb) or ``tty`` (the CDC-ACM serial port the kernel makes of it).
        candidate: True when the ids alone do not prove it is this device (shared ids).
    """

    backend: str
    label: str
    vid: int
    pid: int | None
    node: str = "usb"
    candidate: bool = False

    def __post_init__(self) -> None:
        if self.node not in ("usb", "tty"):
            raise ValueError(f"node must be 'usb' or 'tty', got {self.node!r}")
        for name, value in (("vid", self.vid), ("pid", self.pid)):
            if value is not None and not 0 <= value <= 0xFFFF:
                raise ValueError(f"{name} must be a 16-bit USB id, got {value!r}")

    def matches(self, vid: int, pid: int) -> bool:
        return vid == self.vid and (self.pid is None or pid == self.pid)

    @property
    def ids(self) -> str:
        """``vvvv:pppp`` (``vvvv:*`` for every product)."""
        return f"{self.vid:04x}:{'*' if self.pid is None else f'{self.pid:04x}'}"


def known_identities() -> tuple[UsbIdentity, ...]:
    """Every USB identity a burrforce back-end drives."""
    ids = [
        UsbIdentity("falcon", "Novint Falcon", FALCON_VID, FALCON_PID),
        UsbIdentity("forcedimension", "Force Dimension device", 0x1451, None),
        UsbIdentity("openhaptics", "3D Systems Touch (USB)", 0x0301, 0x2988, node="tty"),
        UsbIdentity("haply", "Haply Inverse3", 0x2FE3, None, node="tty", candidate=True),
        UsbIdentity("haply", "Haply Inverse3", 0x16C0, None, node="tty", candidate=True),
        UsbIdentity("usb", "burrforce vibration board", BOARD_VID, BOARD_PID),
    ]
    return tuple(ids)


def identities_for(backend: str) -> tuple[UsbIdentity, ...]:
    """The identities of one back-end (empty for back-ends without USB hardware)."""
    return tuple(i for i in known_identities() if i.backend == backend)


def match(vid: int, pid: int) -> tuple[UsbIdentity, ...]:
    """The known identities a device with these ids may be."""
    return tuple(i for i in known_identities() if i.matches(vid, pid))


def rule(identity: UsbIdentity) -> str:
    """The udev rule (one line) that lets ``plugdev`` members and the seat's user open the
    device node ``identity`` names."""
    if identity.node == "usb":
        head = ('SUBSYSTEM=="usb", ENV{DEVTYPE}=="usb_device", '
                f'ATTR{{idVendor}}=="{identity.vid:04x}"')
        if identity.pid is not None:
            head += f', ATTR{{idProduct}}=="{identity.pid:04x}"'
    else:  # the tty's own node has no USB attributes: match them on its parent (ATTRS)
        head = f'SUBSYSTEM=="tty", ATTRS{{idVendor}}=="{identity.vid:04x}"'
        if identity.pid is not None:
            head += f', ATTRS{{idProduct}}=="{identity.pid:04x}"'
    return f'{head}, MODE="0660", GROUP="{GROUP}", TAG+="uaccess"'


def rules_file(identities: tuple[UsbIdentity, ...] | None = None) -> str:
    """The text of :data:`RULES_PATH` for ``identities`` (default: all known)."""
    lines = [f"# burrforce: let the seat's user and the {GROUP} group open haptic devices",
             "# and the vibration board. Install with:",
             f"#   sudo cp THIS_FILE {RULES_PATH}",
             *(f"#   {cmd}" for cmd in RELOAD_COMMANDS)]
    for identity in identities if identities is not None else known_identities():
        note = " (candidate ids)" if identity.candidate else ""
        lines += [f"# {identity.label} [{identity.backend}] {identity.ids}{note}", rule(identity)]
    return "\n".join(lines) + "\n"


def access_help(identity: UsbIdentity) -> str:
    """What a user who may not open the device does, as text for an error message."""
    return (f"this user may not open the {identity.label} ({identity.ids}). Add the line\n"
            f"    {rule(identity)}\n"
            f"to {RULES_PATH}, run\n"
            + "".join(f"    {cmd}\n" for cmd in RELOAD_COMMANDS)
            + f"and replug the device (without a local login, also join the group: "
              f"sudo usermod -aG {GROUP} $USER, then log in again).")


def backend_access_help(backend: str) -> str:
    """:func:`access_help` for every identity of ``backend``, joined (empty if it has none)."""
    return "\n".join(access_help(i) for i in identities_for(backend))
