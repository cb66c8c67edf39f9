"""USB device emulation for drivers under test: umockdev + usbfs, no hardware, no privileges.

Our real drivers (pyusb → libusb → usbfs ioctls) run unchanged against emulated devices:

- ``usbfs``: the generic emulator (umockdev testbed, usbfs ioctl handler, unplug/replug);
- ``function``: what an emulated device is (:class:`EmulatedFunction`: descriptors + hooks);
- ``ftdi``, ``falcon``, ``mechanism``: the Novint Falcon (FTDI bridge, bootloader, I/O
  firmware, simulated grip); ``board``: the vibration board; ``loopback``: a test device;
- ``serve`` / ``__main__``: the emulator process; ``control``: its JSON-lines channel;
- ``launcher``: :class:`EmulatedUsb`, which starts that process for tests and benches.

PyGObject and umockdev are imported only when an emulator starts (the emulator process);
:func:`emulation_unavailable_reason` says what is missing.
"""

from .control import EmulatorCommandError
from .function import EmulatedFunction, Endpoint, Stall
from .launcher import EmulatedUsb, emulation_unavailable_reason
from .usbfs import EmulationUnavailable, UsbfsEmulator

__all__ = [
    "EmulatedFunction",
    "EmulatedUsb",
    "EmulationUnavailable",
    "EmulatorCommandError",
    "Endpoint",
    "Stall",
    "UsbfsEmulator",
    "emulation_unavailable_reason",
]
