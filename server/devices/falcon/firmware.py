"""The Falcon's firmware: is it running, and if not, load a user-supplied image through the
bootloader.

The Falcon has no resident application firmware: after every power-on the host uploads one
(it stays until power-off). The images are Novint's, under a noncommercial licence, so
burrforce ships none: the user points ``firmware=`` at ``nvent_firmware.bin`` from libnifalcon
(``firmware/``) or Novint's driver. ``KNOWN_FIRMWARE_SHA256`` only lets us say which image it is.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ..base import DeviceError
from . import protocol as P
from .ftdi import FtdiLink

log = logging.getLogger(__name__)

#: Size bounds of a plausible image (bytes): the known ones are 7–9 KB; the controller's
#: program memory is far below the upper bound.
MIN_FIRMWARE_BYTES = 1024
MAX_FIRMWARE_BYTES = 64 * 1024

#: SHA-256 of the images libnifalcon distributes (firmware/ @ f7c727a), for the log.
KNOWN_FIRMWARE_SHA256 = {
    "1119e39c39fab1f37678ea62dfc715b23dd86ee7f13d78f88f707d9f09b896a1": "nvent_firmware.bin",
    "b2700d5cd5ca217e48565fb4de5a502a636c53f6e01ebd0cad193e9f84856c6a": "test_firmware.bin",
    "ae838730af34b5822c9c3949859b446614af0410730b832cc17a6ad627ea64a4": "novint_T0.bin",
    "e0ae3598670fa1c8d9277bd6943c99b3152b97c400c46c1c42c60de77ff4e816": "novint_T2.bin",
}

#: What to tell a user whose Falcon has no firmware running and who gave no image.
NO_FIRMWARE_HELP = (
    "the Novint Falcon has no firmware running (it forgets it at every power-off) and no "
    "firmware image was given. burrforce cannot ship Novint's firmware (its licence forbids "
    "it): get nvent_firmware.bin from libnifalcon's firmware/ folder "
    "(https://github.com/libnifalcon/libnifalcon) or Novint's driver, and pass "
    "firmware=/path/to/nvent_firmware.bin")

#: I/O cycles the firmware probe tries, and how long each waits for a reply (ms).
PROBE_CYCLES = 10
PROBE_REPLY_TIMEOUT_MS = 20


class FirmwareError(DeviceError):
    """The firmware image is unusable, or loading it into the Falcon failed."""


@dataclass(frozen=True)
class FirmwareImage:
    """A firmware image read from disk.

    Attributes:
        path: where it came from.
        data: its bytes.
        sha256: their SHA-256 (hex).
        known_as: the libnifalcon file name it matches, or None for an unknown image.
    """

    path: Path
    data: bytes
    sha256: str
    known_as: str | None

    def describe(self) -> str:
        what = f"= {self.known_as}" if self.known_as else "not a known image"
        return f"{self.path} ({len(self.data)} B, SHA-256 {self.sha256[:16]}…, {what})"


def read_firmware_image(path: str | os.PathLike[str]) -> FirmwareImage:
    """Read and check a firmware image (FirmwareError when missing, unreadable or of an
    implausible size). An unknown image is accepted with a warning in the log."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise FirmwareError(f"Falcon firmware image {p} does not exist or is not a file")
    size = p.stat().st_size
    if not MIN_FIRMWARE_BYTES <= size <= MAX_FIRMWARE_BYTES:
        raise FirmwareError(
            f"{p} is {size} bytes: not a Falcon firmware image (expected "
            f"{MIN_FIRMWARE_BYTES}..{MAX_FIRMWARE_BYTES} bytes; nvent_firmware.bin is 8492)")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise FirmwareError(f"cannot read Falcon firmware image {p}: {exc}") from exc
    digest = hashlib.sha256(data).hexdigest()
    image = FirmwareImage(p, data, digest, KNOWN_FIRMWARE_SHA256.get(digest))
    if image.known_as is None:
        log.warning("Falcon firmware %s is not one of the images libnifalcon ships; "
                    "trying it anyway", image.describe())
    return image


def firmware_running(link: FtdiLink, cycles: int = PROBE_CYCLES,
                     reply_timeout_ms: int = PROBE_REPLY_TIMEOUT_MS) -> bool:
    """Whether the Falcon answers I/O cycles (zero force) with well-formed status packets.
    Puts the link in normal mode first."""
    link.normal_mode()
    command = P.encode_command((0, 0, 0))
    for _ in range(cycles):
        link.write(command)
        reply = bytearray(link.bulk_read(P.PACKET_BYTES, reply_timeout_ms / 1000.0))
        if any(status is not None for status in P.split_packets(reply, P.decode_status)):
            link.purge()
            return True
    return False


def bootloader_handshake(link: FtdiLink, tries: int = P.FIRMWARE_HANDSHAKE_TRIES) -> None:
    """Reset the Falcon into its bootloader and ready it for an upload (FirmwareError if it
    never answers)."""
    link.bootloader_mode()
    for _ in range(tries):
        link.write(P.FIRMWARE_PROBE)
        # On Linux the reply is exactly the 4 bytes; macOS shows a leading 0x00.
        reply = link.bulk_read(len(P.FIRMWARE_PROBE_REPLY), 0.2)
        if reply.endswith(P.FIRMWARE_PROBE_REPLY):
            break
    else:
        raise FirmwareError(f"the Falcon's bootloader did not answer {tries} handshakes; "
                            "unplug its power and USB, plug them back in and retry")
    link.set_dtr(False)
    link.set_baud_divisor(P.BAUD_DIVISOR_FIRMWARE)
    link.write(P.FIRMWARE_UPLOAD_START)
    echo = link.bulk_read(len(P.FIRMWARE_UPLOAD_START), 1.0)
    if echo != P.FIRMWARE_UPLOAD_START:
        raise FirmwareError(f"the Falcon's bootloader answered {echo!r} to the upload start "
                            f"(expected {P.FIRMWARE_UPLOAD_START!r})")


def upload_firmware(link: FtdiLink, image: FirmwareImage,
                    progress: Callable[[str], None] | None = None) -> None:
    """Send ``image`` in FIRMWARE_CHUNK_BYTES chunks, checking the bootloader's echo of
    every byte (FirmwareError on a mismatch or a missing echo). Call after
    :func:`bootloader_handshake`."""
    data = image.data
    chunk = P.FIRMWARE_CHUNK_BYTES
    for offset in range(0, len(data), chunk):
        part = data[offset:offset + chunk]
        link.write(part, timeout_ms=1000)
        echo = link.bulk_read(len(part), 1.0)
        if len(echo) < len(part):
            raise FirmwareError(f"the Falcon stopped echoing the firmware at byte "
                                f"{offset + len(echo)} of {len(data)}")
        if echo[:len(part)] != part:
            bad = next(i for i in range(len(part)) if echo[i] != part[i])
            raise FirmwareError(f"the Falcon echoed byte {offset + bad} of the firmware as "
                                f"{echo[bad]:#04x}, sent {part[bad]:#04x}: transfer corrupted")
        if progress is not None and (offset // chunk) % 32 == 0:
            progress(f"Falcon firmware: {min(offset + chunk, len(data))}/{len(data)} bytes")


def ensure_firmware(link: FtdiLink, firmware_path: str | os.PathLike[str] | None,
                    progress: Callable[[str], None] | None = None) -> str:
    """Make sure the Falcon runs firmware: probe, and upload ``firmware_path`` only when
    nothing runs. Leaves the link in normal mode. Returns what happened (for the log).
    Raises FirmwareError (with what to do) when no firmware runs and none was given, or the
    upload fails."""
    if firmware_running(link):
        return "firmware already running"
    if firmware_path is None:
        raise FirmwareError(NO_FIRMWARE_HELP)
    image = read_firmware_image(firmware_path)
    if progress is not None:
        progress(f"Falcon: loading firmware {image.describe()}")
    bootloader_handshake(link)
    upload_firmware(link, image, progress)
    if not firmware_running(link, cycles=3 * PROBE_CYCLES):
        raise FirmwareError(f"the Falcon took firmware {image.describe()} but does not answer "
                            "I/O packets: it is not the Novint SDK firmware "
                            "(use nvent_firmware.bin)")
    return f"loaded firmware {image.describe()}"
