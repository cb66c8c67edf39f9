"""A USB device emulated at the Linux usbfs level, in a umockdev testbed.

Real drivers run unchanged against it: pyusb → libusb → ``open("/dev/bus/usb/BBB/DDD")`` +
usbfs ioctls. A client process started with ``LD_PRELOAD=libumockdev-preload.so.0`` and
``UMOCKDEV_DIR=<testbed>`` (see :meth:`UsbfsEmulator.client_env`) sees the testbed's sysfs
(our device's attributes and binary ``descriptors``) and has every ioctl on the device node
forwarded over a Unix socket to this process, where :class:`UsbfsEmulator` answers it from an
:class:`~.function.EmulatedFunction`. The testbed owner and the client are different
processes (as with ``umockdev-run``); the whole client must *start* under the preload.

How libusb (1.0.2x–1.0.30, Linux back-end) drives usbfs, and what we answer:

- every transfer, control ones included, is a URB: SUBMITURB, then the event loop polls the
  fd and reaps with REAPURBNDELAY until EAGAIN. The emulated node is a regular file, so poll
  always reports it ready and libusb spins on REAPURBNDELAY while it waits; we hold an
  empty-handed reap up to ``reap_hold_s`` (answering at once when data appears) so the spin
  costs two context switches per ``reap_hold_s`` instead of burning both cores;
- OUT and control URBs complete at submission; IN URBs complete when the function produces
  data (:meth:`~.function.EmulatedFunction.in_`), polled on every reap and on ``wake()``;
- a libusb timeout DISCARDURBs a pending URB: it is reaped with status −ENOENT;
- :meth:`UsbfsEmulator.unplug` completes pending URBs with −ESHUTDOWN (libusb:
  LIBUSB_TRANSFER_NO_DEVICE), answers every later ioctl with ENODEV (REAP after disconnect
  still drains completed URBs, as USBDEVFS_CAP_REAP_AFTER_DISCONNECT promises), and removes
  the device from sysfs, so pyusb raises ``USBError`` errno 19 on the next transfer and
  ``usb.core.find`` no longer finds it.

Limits: one configuration, interface 0 with alternate setting 0, no isochronous endpoints; a
device-side poll() never reports POLLERR (a real unplug wakes a *blocked* libusb at once; here
libusb notices on its next reap, which it issues continuously while a transfer is pending).

Struct layouts (x86-64/aarch64, LP64) and ioctl numbers from ``linux/usbdevice_fs.h``.
"""

from __future__ import annotations

import errno
import heapq
import os
import shutil
import struct
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from .function import DIR_IN, EmulatedFunction, Endpoint, Stall

__all__ = [
    "EmulatedFunction",
    "EmulationUnavailable",
    "Endpoint",
    "Stall",
    "UsbfsEmulator",
    "preload_library",
    "require_umockdev",
]

PRELOAD_NAME = "libumockdev-preload.so.0"
#: Where Debian/Ubuntu/Fedora/Arch put the preload library (multiarch first).
PRELOAD_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64",
                "/usr/lib", "/usr/local/lib", "/usr/local/lib64")
INSTALL_HINT = ("install umockdev with its GObject introspection data (Debian/Ubuntu: "
                "'apt-get install umockdev libumockdev0 gir1.2-umockdev-1.0') and PyGObject "
                "('pip install \"burrforce[emulation]\"' or Debian's python3-gi)")


class EmulationUnavailable(RuntimeError):
    """umockdev, its preload library or PyGObject is missing; the message says what to
    install."""


def preload_library() -> str:
    """Path of ``libumockdev-preload.so.0`` ($BURRFORCE_UMOCKDEV_PRELOAD overrides the search);
    EmulationUnavailable when it is not installed."""
    override = os.environ.get("BURRFORCE_UMOCKDEV_PRELOAD")
    candidates = [override] if override else [os.path.join(d, PRELOAD_NAME)
                                              for d in PRELOAD_DIRS]
    for path in candidates:
        if path and os.path.isfile(path):
            return path
    raise EmulationUnavailable(f"{PRELOAD_NAME} not found (looked in "
                               f"{', '.join(c for c in candidates if c)}); {INSTALL_HINT}")


def require_umockdev() -> Any:
    """The ``gi.repository.UMockdev`` module; EmulationUnavailable naming what to install."""
    try:
        import gi
    except ImportError as exc:
        raise EmulationUnavailable(f"PyGObject (gi) is not importable: {exc}; "
                                   f"{INSTALL_HINT}") from None
    try:
        gi.require_version("UMockdev", "1.0")
        from gi.repository import UMockdev
    except (ImportError, ValueError) as exc:
        raise EmulationUnavailable(f"UMockdev 1.0 typelib not available: {exc}; "
                                   f"{INSTALL_HINT}") from None
    return UMockdev


# -- usbfs ABI -------------------------------------------------------------------------------

def _ioc(direction: int, nr: int, size: int) -> int:
    """Linux's _IOC(dir, 'U', nr, size); dir 0 none, 1 write, 2 read, 3 both."""
    return (direction << 30) | (size << 16) | (ord("U") << 8) | nr


URB_STRUCT_BYTES = 56        # struct usbdevfs_urb without iso descriptors
URB_STATUS_OFFSET = 4
URB_BUFFER_OFFSET = 16
URB_ACTUAL_OFFSET = 28
CTRL_STRUCT_BYTES = 24       # struct usbdevfs_ctrltransfer
CTRL_DATA_OFFSET = 16
BULK_STRUCT_BYTES = 24       # struct usbdevfs_bulktransfer
BULK_DATA_OFFSET = 16
SETUP_BYTES = 8

IOCTL_CONTROL = _ioc(3, 0, CTRL_STRUCT_BYTES)
IOCTL_BULK = _ioc(3, 2, BULK_STRUCT_BYTES)
IOCTL_RESETEP = _ioc(2, 3, 4)
IOCTL_SETINTERFACE = _ioc(2, 4, 8)
IOCTL_SETCONFIGURATION = _ioc(2, 5, 4)
IOCTL_GETDRIVER = _ioc(1, 8, 260)
IOCTL_SUBMITURB = _ioc(2, 10, URB_STRUCT_BYTES)
IOCTL_DISCARDURB = _ioc(0, 11, 0)
IOCTL_REAPURB = _ioc(1, 12, 8)
IOCTL_REAPURBNDELAY = _ioc(1, 13, 8)
IOCTL_CLAIMINTERFACE = _ioc(2, 15, 4)
IOCTL_RELEASEINTERFACE = _ioc(2, 16, 4)
IOCTL_CONNECTINFO = _ioc(1, 17, 8)
IOCTL_IOCTL = _ioc(3, 18, 16)
IOCTL_RESET = _ioc(0, 20, 0)
IOCTL_CLEAR_HALT = _ioc(2, 21, 4)
IOCTL_DISCONNECT = _ioc(0, 22, 0)
IOCTL_GET_CAPABILITIES = _ioc(2, 26, 4)
IOCTL_DISCONNECT_CLAIM = _ioc(2, 27, 264)
IOCTL_DROP_PRIVILEGES = _ioc(1, 30, 4)
IOCTL_GET_SPEED = _ioc(0, 31, 0)

URB_TYPE_INTERRUPT = 1
URB_TYPE_CONTROL = 2
URB_TYPE_BULK = 3

# One URB per transfer of any length (scatter-gather, no packet-size limit), reap after
# disconnect, zero-length packets. No MMAP: libusb would map the (regular-file) node.
CAPABILITIES = 0x01 | 0x04 | 0x08 | 0x10
USB_SPEED_CODES = {1.5: 1, 12: 2, 480: 3}
USB_DEVICE_MAJOR = 189

IOCTL_NAMES = {v: k[6:] for k, v in list(globals().items()) if k.startswith("IOCTL_")}


@dataclass
class _Urb:
    """A submitted URB: its struct and buffer resolved into our memory."""

    client: Any
    struct: Any             # UMockdev.IoctlData, URB_STRUCT_BYTES
    buffer: Any             # UMockdev.IoctlData of buffer_length bytes, or None
    client_addr: int
    kind: int
    endpoint: int
    length: int

    def finish(self, status: int, payload: bytes = b"", offset: int = 0,
               actual: int | None = None) -> None:
        if payload:
            self.buffer.update(offset, payload)
        done = len(payload) if actual is None else actual
        self.struct.update(URB_STATUS_OFFSET, struct.pack("<i", status))
        self.struct.update(URB_ACTUAL_OFFSET, struct.pack("<i", done))


@dataclass(order=True)
class _HeldReap:
    """A reap we have not answered yet: answered with a URB when one completes, else with
    EAGAIN (REAPURBNDELAY) at ``deadline_ns``; REAPURB waits without deadline."""

    deadline_ns: float
    seq: int
    client: Any = field(compare=False)
    target: Any = field(compare=False)   # the resolved `struct usbdevfs_urb **`
    done: bool = field(default=False, compare=False)


class UsbfsEmulator:
    """Serve one :class:`EmulatedFunction` as ``/dev/bus/usb/<bus>/<devnum>`` in a fresh
    umockdev testbed (this process owns it; clients run elsewhere under
    :meth:`client_env`).

    Args:
        function: the device.
        bus, devnum: its USB address (1..127 each).
        reap_hold_s: longest time an empty-handed REAPURBNDELAY is held (see module doc).
    """

    def __init__(self, function: EmulatedFunction, bus: int = 1, devnum: int = 2,
                 reap_hold_s: float = 0.0005) -> None:
        function.validate()
        if not 1 <= bus <= 127 or not 1 <= devnum <= 127:
            raise ValueError(f"bus and devnum must be 1..127, got {bus}, {devnum}")
        if not 0.0 <= reap_hold_s <= 0.1:
            raise ValueError(f"reap_hold_s must be 0..0.1 s, got {reap_hold_s}")
        self.function = function
        self.bus = bus
        self.devnum = devnum
        self.reap_hold_ns = int(reap_hold_s * 1e9)
        self.node = f"/dev/bus/usb/{bus:03d}/{devnum:03d}"
        self.lock = threading.RLock()
        self.unplugged = False
        # Each plug-in is a generation; a client (an open fd) belongs to the generation it
        # opened in, and an fd from before an unplug stays dead after a replug, as in Linux.
        self.generation = 0
        self._client_generation: dict[Any, int] = {}
        self.ioctl_counts: dict[str, int] = {}
        self._pending: list[_Urb] = []
        self._reapable: dict[Any, deque[_Urb]] = {}
        self._held: list[_HeldReap] = []
        self._held_seq = 0
        self._wake = threading.Condition(threading.Lock())
        self._woken = False
        self._stopping = False
        self._pump: threading.Thread | None = None
        self._testbed: Any = None
        self._handler: Any = None
        self.syspath: str | None = None
        self.root_dir: str | None = None
        self._preload = ""

    # -- lifecycle ---------------------------------------------------------------------

    def start(self) -> UsbfsEmulator:
        """Create the testbed, the device and its ioctl handler. EmulationUnavailable when
        umockdev is missing."""
        UMockdev = require_umockdev()
        self._preload = preload_library()
        self._testbed = UMockdev.Testbed.new()
        self.root_dir = self._testbed.get_root_dir()
        self._add_device()
        f = self.function
        f._waker = self.wake
        self._handler = UMockdev.IoctlBase()
        self._handler.connect("handle-ioctl", self._on_ioctl)
        self._handler.connect("client-connected", self._on_client_connected)
        self._handler.connect("client-vanished", self._on_client_vanished)
        self._testbed.attach_ioctl(self.node, self._handler)
        self._pump = threading.Thread(target=self._pump_loop, name="usbfs-pump", daemon=True)
        self._pump.start()
        return self

    def _add_device(self) -> None:
        """The device's sysfs entry (attributes, binary descriptors) and its node file."""
        f = self.function
        minor = (self.bus - 1) * 128 + (self.devnum - 1)
        vid, pid = f"{f.vendor_id:04x}", f"{f.product_id:04x}"
        speed = "1.5" if f.speed_mbps == 1.5 else str(int(f.speed_mbps))
        attributes = ["busnum", str(self.bus), "devnum", str(self.devnum), "speed", speed,
                      "idVendor", vid, "idProduct", pid, "bcdDevice", f"{f.bcd_device:04x}",
                      "bConfigurationValue", "1", "bNumConfigurations", "1",
                      "bNumInterfaces", " 1", "bMaxPacketSize0", str(f.max_packet_ep0),
                      "dev", f"{USB_DEVICE_MAJOR}:{minor}"]
        for name, value in (("manufacturer", f.manufacturer), ("product", f.product),
                            ("serial", f.serial)):
            if value is not None:
                attributes += [name, value]
        properties = ["DEVNAME", self.node, "DEVTYPE", "usb_device", "SUBSYSTEM", "usb",
                      "BUSNUM", f"{self.bus:03d}", "DEVNUM", f"{self.devnum:03d}",
                      "MAJOR", str(USB_DEVICE_MAJOR), "MINOR", str(minor),
                      "PRODUCT", f"{f.vendor_id:x}/{f.product_id:x}/{f.bcd_device:x}"]
        self.syspath = self._testbed.add_device("usb", f"usb{self.bus}/{self.bus}-1", None,
                                                attributes, properties)
        if not self.syspath:
            raise EmulationUnavailable("umockdev refused to add the USB device")
        self._testbed.set_attribute_binary(self.syspath, "descriptors", f.descriptors())
        node_file = os.path.join(self.root_dir, self.node.lstrip("/"))
        os.makedirs(os.path.dirname(node_file), exist_ok=True)
        with open(node_file, "wb"):
            pass

    def client_env(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """The environment a client process must *start* with (``base`` defaults to none:
        merge it into os.environ yourself)."""
        if self.root_dir is None:
            raise RuntimeError("start the emulator first")
        env = dict(base or {})
        preload = env.get("LD_PRELOAD", "")
        env["LD_PRELOAD"] = f"{self._preload}:{preload}" if preload else self._preload
        env["UMOCKDEV_DIR"] = self.root_dir
        return env

    def stop(self) -> None:
        """Stop serving and delete the testbed directory. Clients still attached get EOF on
        their ioctl socket (libumockdev-preload aborts them): stop clients first."""
        with self._wake:
            self._stopping = True
            self._wake.notify()
        if self._pump is not None:
            self._pump.join(timeout=2.0)
        if self._testbed is not None:
            try:
                self._testbed.detach_ioctl(self.node)
            except Exception:  # best effort during teardown
                pass
            root = self.root_dir
            self._testbed = None
            self._handler = None
            if root:
                shutil.rmtree(root, ignore_errors=True)

    def wake(self) -> None:
        """Retry pending IN URBs and held reaps now (thread-safe, never blocks long)."""
        with self._wake:
            self._woken = True
            self._wake.notify()

    def unplug(self) -> None:
        """Pull the plug: pending URBs end with −ESHUTDOWN, later ioctls fail with ENODEV,
        the device leaves sysfs. No uevent: umockdev builds uevents with libudev in *this*
        process, which is not preloaded (and libusb's netlink monitor ignores them anyway)."""
        with self.lock:
            if self.unplugged:
                return
            self.unplugged = True
            self.function.power_off()
            for urb in self._pending:
                urb.finish(-errno.ESHUTDOWN)
                self._reapable.setdefault(urb.client, deque()).append(urb)
            self._pending.clear()
            self._answer_held(time.monotonic_ns())
            if self._testbed is not None and self.syspath:
                self._testbed.remove_device(self.syspath)
        self.wake()

    def replug(self) -> None:
        """Plug the device back in, freshly powered (``EmulatedFunction.power_cycle``). Fds
        opened before the unplug stay dead; the host must open the device again."""
        with self.lock:
            if not self.unplugged:
                return
            self.function.power_cycle()
            self.generation += 1
            self._add_device()
            self.unplugged = False

    def stats(self) -> dict[str, Any]:
        """Counts of the ioctls served (by name), URBs pending, whether unplugged."""
        with self.lock:
            return {"ioctls": dict(self.ioctl_counts), "pending_urbs": len(self._pending),
                    "unplugged": self.unplugged, "node": self.node, "bus": self.bus,
                    "devnum": self.devnum}

    # -- ioctl dispatch (umockdev's worker thread) -------------------------------------

    def _on_client_connected(self, _handler: Any, client: Any) -> None:
        with self.lock:
            self._client_generation[client] = self.generation

    def _on_client_vanished(self, _handler: Any, client: Any) -> None:
        with self.lock:
            self._client_generation.pop(client, None)
            self._pending = [u for u in self._pending if u.client is not client]
            self._reapable.pop(client, None)
            for held in self._held:
                if held.client is client:
                    held.done = True

    def _on_ioctl(self, _handler: Any, client: Any) -> bool:
        request = client.get_request()
        name = IOCTL_NAMES.get(request, f"{request:#x}")
        with self.lock:
            self.ioctl_counts[name] = self.ioctl_counts.get(name, 0) + 1
            try:
                self._dispatch(client, request)
            except Exception:  # a bug here must not hang the client
                print(f"usbfs emulator: {name} failed:", file=sys.stderr)
                traceback.print_exc()
                client.complete(-1, errno.EIO)
        return True

    def _gone(self, client: Any) -> bool:
        """Whether ``client``'s device is unplugged (now, or since it opened the node)."""
        return self.unplugged or self._client_generation.get(client, self.generation) \
            != self.generation

    def _dispatch(self, client: Any, request: int) -> None:
        if request in (IOCTL_REAPURB, IOCTL_REAPURBNDELAY):
            self._reap(client, blocking=request == IOCTL_REAPURB)
            return
        if self._gone(client):
            client.complete(-1, errno.ENODEV)
            return
        arg = client.get_arg()
        if request == IOCTL_SUBMITURB:
            self._submit(client, arg)
        elif request == IOCTL_DISCARDURB:
            (addr,) = struct.unpack("<Q", bytes(arg.retrieve())[:8])
            self._discard(client, addr)
        elif request == IOCTL_GET_CAPABILITIES:
            arg.resolve(0, 4).update(0, struct.pack("<I", CAPABILITIES))
            client.complete(0, 0)
        elif request == IOCTL_CONNECTINFO:
            arg.resolve(0, 8).update(0, struct.pack("<IB3x", self.devnum,
                                                     int(self.function.speed_mbps == 1.5)))
            client.complete(0, 0)
        elif request == IOCTL_GET_SPEED:
            client.complete(USB_SPEED_CODES[self.function.speed_mbps], 0)
        elif request in (IOCTL_CLAIMINTERFACE, IOCTL_RELEASEINTERFACE, IOCTL_DISCONNECT_CLAIM):
            (iface,) = struct.unpack("<I", bytes(arg.resolve(0, 4).retrieve()))
            client.complete(*((0, 0) if iface == 0 else (-1, errno.ENOENT)))
        elif request == IOCTL_SETINTERFACE:
            iface, alt = struct.unpack("<II", bytes(arg.resolve(0, 8).retrieve()))
            client.complete(*((0, 0) if (iface, alt) == (0, 0) else (-1, errno.EINVAL)))
        elif request == IOCTL_SETCONFIGURATION:
            (config,) = struct.unpack("<i", bytes(arg.resolve(0, 4).retrieve()))
            client.complete(*((0, 0) if config in (-1, 0, 1) else (-1, errno.EINVAL)))
        elif request == IOCTL_CLEAR_HALT:
            (ep,) = struct.unpack("<I", bytes(arg.resolve(0, 4).retrieve()))
            if self.function.endpoint(ep & 0xFF) is None:
                client.complete(-1, errno.ENOENT)
            else:
                self.function.clear_halt(ep & 0xFF)
                client.complete(0, 0)
        elif request in (IOCTL_RESETEP, IOCTL_DROP_PRIVILEGES):
            client.complete(0, 0)
        elif request == IOCTL_RESET:
            self.function.bus_reset()
            client.complete(0, 0)
        elif request in (IOCTL_GETDRIVER, IOCTL_IOCTL, IOCTL_DISCONNECT):
            client.complete(-1, errno.ENODATA)   # no kernel driver bound
        elif request == IOCTL_CONTROL:
            self._sync_control(client, arg)
        elif request == IOCTL_BULK:
            self._sync_bulk(client, arg)
        else:
            client.complete(-1, errno.ENOTTY)

    # -- URBs ------------------------------------------------------------------------

    def _submit(self, client: Any, arg: Any) -> None:
        (addr,) = struct.unpack("<Q", bytes(arg.retrieve())[:8])
        data = arg.resolve(0, URB_STRUCT_BYTES)
        kind, endpoint, _status, _flags, _buf, length = struct.unpack(
            "<BBxxiI4xQi", bytes(data.retrieve())[:28])
        if length < 0:
            client.complete(-1, errno.EINVAL)
            return
        ep = self.function.endpoint(endpoint) if endpoint & 0x7F else None
        if kind == URB_TYPE_CONTROL:
            if endpoint & 0x7F or length < SETUP_BYTES:
                client.complete(-1, errno.EINVAL)
                return
        elif kind in (URB_TYPE_BULK, URB_TYPE_INTERRUPT):
            if ep is None:
                client.complete(-1, errno.ENOENT)
                return
            if kind == URB_TYPE_INTERRUPT and ep.transfer != "interrupt":
                client.complete(-1, errno.EINVAL)
                return
        else:
            client.complete(-1, errno.EINVAL)   # isochronous: not emulated
            return
        buffer = data.resolve(URB_BUFFER_OFFSET, length) if length else None
        urb = _Urb(client, data, buffer, addr, kind, endpoint, length)
        client.complete(0, 0)
        if kind == URB_TYPE_CONTROL:
            self._run_control(urb)
        elif endpoint & DIR_IN:
            self._pending.append(urb)
            self._poll_in()
            return
        else:
            payload = bytes(buffer.retrieve()) if buffer is not None else b""
            try:
                self.function.out(endpoint, payload)
                urb.finish(0, actual=len(payload))
            except Stall:
                urb.finish(-errno.EPIPE, actual=0)
            self._poll_in()   # an OUT often makes IN data (a command's reply)
        self._reapable.setdefault(client, deque()).append(urb)
        self._answer_held(time.monotonic_ns())

    def _control(self, setup: tuple[int, int, int, int, int], data: bytes) -> bytes:
        """One control transfer on the function: the IN reply (at most wLength bytes), b""
        for an OUT. Raises Stall when the function refuses it."""
        rtype, req, value, index, wlength = setup
        if rtype & DIR_IN:
            answer = self.function.control(rtype, req, value, index, wlength)
            if answer is None or isinstance(answer, int):
                raise Stall
            return bytes(answer)[:wlength]
        if self.function.control(rtype, req, value, index, data) is None:
            raise Stall
        return b""

    def _run_control(self, urb: _Urb) -> None:
        raw = bytes(urb.buffer.retrieve())
        rtype, req, value, index, wlength = struct.unpack("<BBHHH", raw[:SETUP_BYTES])
        wlength = min(wlength, urb.length - SETUP_BYTES)
        try:
            reply = self._control((rtype, req, value, index, wlength),
                                  raw[SETUP_BYTES:SETUP_BYTES + wlength])
        except Stall:
            urb.finish(-errno.EPIPE, actual=0)
            return
        if rtype & DIR_IN:
            urb.finish(0, reply, offset=SETUP_BYTES)
        else:
            urb.finish(0, actual=wlength)

    def _poll_in(self) -> None:
        """Ask the function for data for each pending IN URB, oldest first per endpoint."""
        blocked: set[tuple[int, Any]] = set()
        done: list[_Urb] = []
        for urb in self._pending:
            key = (urb.endpoint, urb.client)
            if key in blocked:
                continue
            try:
                answer = self.function.in_(urb.endpoint, urb.length)
            except Stall:
                urb.finish(-errno.EPIPE, actual=0)
                done.append(urb)
                continue
            if answer is None:
                blocked.add(key)
                continue
            answer = bytes(answer)
            if len(answer) > urb.length:
                urb.finish(-errno.EOVERFLOW, answer[:urb.length])
            else:
                urb.finish(0, answer)
            done.append(urb)
        for urb in done:
            self._pending.remove(urb)
            self._reapable.setdefault(urb.client, deque()).append(urb)

    def _discard(self, client: Any, addr: int) -> None:
        for urb in self._pending:
            if urb.client is client and urb.client_addr == addr:
                self._pending.remove(urb)
                urb.finish(-errno.ENOENT, actual=0)
                self._reapable.setdefault(client, deque()).append(urb)
                client.complete(0, 0)
                self._answer_held(time.monotonic_ns())
                return
        client.complete(-1, errno.EINVAL)   # already completed: libusb reaps it normally

    def _reap(self, client: Any, blocking: bool) -> None:
        gone = self._gone(client)
        if not gone:
            self._poll_in()
        queue = self._reapable.get(client)
        if queue:
            self._give_urb(client, client.get_arg().resolve(0, 8), queue.popleft())
            return
        if gone:
            client.complete(-1, errno.ENODEV)
            return
        has_pending = any(u.client is client for u in self._pending)
        if not blocking and (not has_pending or self.reap_hold_ns == 0):
            client.complete(-1, errno.EAGAIN)
            return
        self._held_seq += 1
        deadline = float("inf") if blocking else time.monotonic_ns() + self.reap_hold_ns
        heapq.heappush(self._held, _HeldReap(deadline, self._held_seq, client,
                                             client.get_arg().resolve(0, 8)))
        self.wake()

    @staticmethod
    def _give_urb(client: Any, target: Any, urb: _Urb) -> None:
        target.set_ptr(0, urb.struct)
        client.complete(0, 0)

    def _answer_held(self, now_ns: int) -> None:
        """Answer held reaps that have a URB now, or whose deadline passed (EAGAIN)."""
        keep: list[_HeldReap] = []
        for held in self._held:
            if held.done:
                continue
            queue = self._reapable.get(held.client)
            if queue:
                self._give_urb(held.client, held.target, queue.popleft())
            elif self._gone(held.client):
                held.client.complete(-1, errno.ENODEV)
            elif held.deadline_ns <= now_ns:
                held.client.complete(-1, errno.EAGAIN)
            else:
                keep.append(held)
                continue
            held.done = True
        heapq.heapify(keep)
        self._held = keep

    def _pump_loop(self) -> None:
        # Lock order: never take self.lock while holding self._wake (hooks call wake()
        # with self.lock held).
        while True:
            with self.lock:
                deadline = self._held[0].deadline_ns if self._held else None
            timeout = 0.5 if deadline is None else min(
                0.5, max(0.0, (deadline - time.monotonic_ns()) * 1e-9))
            with self._wake:
                if self._stopping:
                    return
                if not self._woken and timeout > 0.0:
                    self._wake.wait(timeout)
                self._woken = False
                if self._stopping:
                    return
            with self.lock:
                if self._held and not self.unplugged:
                    self._poll_in()
                self._answer_held(time.monotonic_ns())

    # -- synchronous ioctls (libusb does not use them; other usbfs clients may) ---------

    def _sync_control(self, client: Any, arg: Any) -> None:
        ctrl = arg.resolve(0, CTRL_STRUCT_BYTES)
        setup = struct.unpack("<BBHHH", bytes(ctrl.retrieve())[:8])
        rtype, wlength = setup[0], setup[4]
        buf = ctrl.resolve(CTRL_DATA_OFFSET, wlength) if wlength else None
        payload = bytes(buf.retrieve()) if buf is not None and not rtype & DIR_IN else b""
        try:
            reply = self._control(setup, payload)
        except Stall:
            client.complete(-1, errno.EPIPE)
            return
        if rtype & DIR_IN:
            if reply:
                buf.update(0, reply)
            client.complete(len(reply), 0)
        else:
            client.complete(wlength, 0)

    def _sync_bulk(self, client: Any, arg: Any) -> None:
        bulk = arg.resolve(0, BULK_STRUCT_BYTES)
        endpoint, length, _timeout = struct.unpack("<III", bytes(bulk.retrieve())[:12])
        if self.function.endpoint(endpoint & 0xFF) is None:
            client.complete(-1, errno.ENOENT)
            return
        buf = bulk.resolve(BULK_DATA_OFFSET, length) if length else None
        try:
            if endpoint & DIR_IN:
                answer = self.function.in_(endpoint, length)
                if answer is None:
                    client.complete(-1, errno.ETIMEDOUT)
                    return
                reply = bytes(answer)[:length]
                if reply:
                    buf.update(0, reply)
                client.complete(len(reply), 0)
            else:
                payload = bytes(buf.retrieve()) if buf is not None else b""
                self.function.out(endpoint, payload)
                client.complete(length, 0)
        except Stall:
            client.complete(-1, errno.EPIPE)
