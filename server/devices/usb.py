"""What every USB back-end shares: the libusb backend pyusb runs on, and pyusb's errors turned
into the ``DeviceError`` family with what to do about them."""

from __future__ import annotations

import errno
from typing import Any

from .base import DeviceAccessDenied, DeviceDisconnected, DeviceError, VendorLibraryMissing

# libusb error codes, for errors pyusb raises without an errno.
_LIBUSB_IO, _LIBUSB_ACCESS, _LIBUSB_NO_DEVICE, LIBUSB_NOT_FOUND = -1, -3, -4, -5
_LIBUSB_BUSY, LIBUSB_TIMEOUT, _LIBUSB_PIPE = -6, -7, -9
_GONE_ERRNOS = {errno.ENODEV, errno.EIO, errno.ENOENT, errno.EPIPE, errno.ESHUTDOWN}
_GONE_CODES = {_LIBUSB_IO, _LIBUSB_NO_DEVICE, LIBUSB_NOT_FOUND, _LIBUSB_PIPE}
_DENIED_ERRNOS = {errno.EACCES, errno.EPERM}


def find_libusb() -> tuple[Any, str]:
    """(pyusb libusb-1.0 backend, which library it is) — libusb-package's bundled library,
    else the system's — or (None, why there is none and what to install)."""
    try:
        import usb.backend.libusb1 as libusb1
    except ImportError:
        return None, "pyusb is not installed: pip install pyusb libusb-package"
    try:
        import libusb_package
    except ImportError:
        pass
    else:
        backend = libusb_package.get_libusb1_backend()
        if backend is not None:
            return backend, f"libusb-package ({libusb_package.get_library_path()})"
    backend = libusb1.get_backend()
    if backend is not None:
        return backend, "system libusb-1.0"
    return None, ("no libusb-1.0 found: pip install libusb-package, or apt-get install "
                  "libusb-1.0-0")


def libusb_backend(label: str) -> Any:
    """The pyusb backend :func:`find_libusb` finds.

    Raises:
        VendorLibraryMissing: none (``label`` names the device that needs it).
    """
    backend, description = find_libusb()
    if backend is None:
        raise VendorLibraryMissing(f"the {label} needs libusb: {description}")
    return backend


def usb_error(exc: BaseException, doing: str, label: str, access_help: str = "",
              gone_hint: str = "check its USB cable", busy_hint: str = "") -> DeviceError:
    """The DeviceError for a pyusb error raised while ``doing`` with the device ``label``:
    unplugged or reset → DeviceDisconnected, no permission → DeviceAccessDenied (with
    ``access_help``: the udev rule), busy or timed out → DeviceError saying so."""
    if isinstance(exc, DeviceError):
        return exc
    err = getattr(exc, "errno", None)
    code = getattr(exc, "backend_error_code", None)
    if err in _DENIED_ERRNOS or code == _LIBUSB_ACCESS:
        return DeviceAccessDenied(f"no permission to use the {label} ({doing}: {exc}); "
                                  f"{access_help}")
    if err in _GONE_ERRNOS or code in _GONE_CODES:
        return DeviceDisconnected(f"the {label} went away ({doing}: {exc}); {gone_hint}")
    if err == errno.EBUSY or code == _LIBUSB_BUSY:
        return DeviceError(f"the {label} is busy ({doing}: {exc}); another program "
                           f"{busy_hint or 'has it open'}")
    if err == errno.ETIMEDOUT or code == LIBUSB_TIMEOUT:
        return DeviceError(f"the {label} did not answer in time ({doing}: {exc})")
    return DeviceError(f"USB error {doing}: {exc}")


def is_timeout(exc: BaseException) -> bool:
    """Whether a pyusb error is a transfer timeout (nothing to read yet, not a failure)."""
    return (getattr(exc, "backend_error_code", None) == LIBUSB_TIMEOUT
            or getattr(exc, "errno", None) == errno.ETIMEDOUT)
