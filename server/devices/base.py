"""What a haptic device is and what one I/O cycle with it does.

Modelled on CHAI3D's generic device (``cGenericHapticDevice``): a device describes itself
(:class:`DeviceInfo`) and exchanges force for state in **one** call, :meth:`HapticDevice.cycle`,
because the Falcon and the Inverse3 do exactly that in one USB transaction. The device loop
(``devices.loop``) owns pacing, the coupling model and the watchdog; a back-end only talks to
its hardware.

Frames and units: each device reports positions in its own (native) right-handed frame, in mm,
with the origin at its workspace centre (``DeviceInfo.workspace_radius_mm`` around it); forces
are N in the same frame. ``DeviceInfo.axes`` turns native axes into burrforce's common device
frame, CHAI3D's: x toward the user, y to the user's right, z up. The device loop works in the
common frame, and ``devices.mapping`` places that in the bone's, so the same placement means
the same thing on every device.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from ..haptics.profiles import DeviceProfile

log = logging.getLogger(__name__)


class DeviceError(RuntimeError):
    """A device failed: not found, not accessible, a USB error, a vendor library missing."""


class DeviceNotFound(DeviceError):
    """No such device is plugged in (or its back-end cannot see it)."""


class DeviceAccessDenied(DeviceError):
    """The device is there but this user may not open it (on Linux: a udev rule is missing;
    the message says which)."""


class DeviceDisconnected(DeviceError):
    """The device went away mid-stream (unplugged, powered off, the bus reset)."""


class VendorLibraryMissing(DeviceError):
    """A vendor back-end's Python package or native SDK is not installed; the message says
    what to install."""


@dataclass(frozen=True)
class DeviceInfo:
    """What a device is.

    Attributes:
        backend: the back-end's name (``sim``, ``falcon``, ...).
        model: the device's model as its maker names it.
        limits: what it renders stably: the matching ``haptics.profiles`` profile (max force,
            rated coupling stiffness and damping at ``limits.rated_hz``, slew, resolution).
        workspace_radius_mm: radius of the sphere around the origin the end effector reaches.
        servo_rate_hz: the I/O cycle rate the device is meant to run at.
        buttons: how many user switches :attr:`DeviceState.buttons` reports.
        sensed_rotation: whether the state carries the handle's orientation.
        serial: the unit's serial number or bus address, when known.
        axes: (3, 3) rows: the common frame's x, y, z in native axes (common = axes ·
            native); identity when the back-end already reports CHAI3D's axes.
    """

    backend: str
    model: str
    limits: DeviceProfile
    workspace_radius_mm: float
    servo_rate_hz: float
    buttons: int = 0
    sensed_rotation: bool = False
    serial: str | None = None
    axes: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0),
                                                    (0.0, 0.0, 1.0))

    def as_dict(self) -> dict:
        return {"backend": self.backend, "model": self.model, "limits": self.limits.as_dict(),
                "workspace_radius_mm": self.workspace_radius_mm,
                "servo_rate_hz": self.servo_rate_hz, "buttons": self.buttons,
                "sensed_rotation": self.sensed_rotation, "serial": self.serial,
                "axes": [list(row) for row in self.axes]}


@dataclass
class DeviceState:
    """One cycle's reading, in the device's frame.

    Attributes:
        position_mm: (3,) end-effector position, mm, relative to the workspace centre.
        velocity_mm_s: (3,) its velocity, mm/s (measured, or estimated by the back-end).
        buttons: bit i set while switch i is pressed.
        t_ns: when the reading was taken, ``time.monotonic_ns()`` (or the simulated clock).
        rotation: (3, 3) the handle's orientation (columns: its axes in the device frame),
            or None when the device senses no rotation.
    """

    position_mm: np.ndarray
    velocity_mm_s: np.ndarray
    buttons: int = 0
    t_ns: int = 0
    rotation: np.ndarray | None = field(default=None)


_Output = TypeVar("_Output", bound="SafeOutput")


class SafeOutput(ABC):
    """Hardware that is opened once and left safe when closed (a haptic device: zero force;
    an actuator: silence). ``close`` makes it safe (:meth:`_make_safe`), then releases it
    (:meth:`_close`); an ``open`` that fails or is stopped part-way releases whatever the
    back-end got to. Use as a context manager."""

    def __init__(self) -> None:
        self._opened = False

    @property
    def is_open(self) -> bool:
        return self._opened

    def open(self) -> None:
        """Acquire the hardware (raises the DeviceError family with what to do)."""
        if not self._opened:
            try:
                self._open()
                self._opened = True
            except BaseException:
                # Failed or stopped part-way (a stop signal, a second part missing): release
                # whatever the back-end got to; its error is the one to report.
                release_after_failed_open(self._close)
                raise

    def close(self) -> None:
        """Make the output safe and release it. Safe to call twice."""
        if self._opened:
            try:
                self._make_safe()
            finally:
                self._opened = False
                self._close()

    @abstractmethod
    def _make_safe(self) -> None:
        """Leave the output harmless (best effort: never raises)."""

    @abstractmethod
    def _open(self) -> None:
        """Acquire the hardware."""

    @abstractmethod
    def _close(self) -> None:
        """Release what ``_open`` acquired. Also called when ``_open`` raised part-way, so it
        must release only what is there (and be safe to call twice)."""

    def __enter__(self: _Output) -> _Output:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class HapticDevice(SafeOutput):
    """A haptic device back-end. Use as a context manager: ``close`` always zeroes the force.

    Subclasses set :attr:`info` and implement :meth:`_open`, :meth:`cycle`, :meth:`_close`;
    :meth:`home` defaults to "nothing to home". A constructor only checks its options (the
    server builds a back-end once to refuse bad ones before starting a device process);
    :meth:`open` is where the hardware or vendor library is touched.
    """

    info: DeviceInfo

    def home(self, timeout_s: float = 30.0,
             progress: Callable[[str], None] | None = None,
             cancelled: Callable[[], bool] | None = None) -> bool:
        """Bring the device to a known position reference (the Falcon: the user moves the
        grip through its range). True once homed; False if ``timeout_s`` passed first or
        ``cancelled()`` became true (checked every cycle where the back-end waits).
        ``progress`` receives instructions for the user."""
        return True

    @abstractmethod
    def cycle(self, force_N: np.ndarray) -> DeviceState:
        """One I/O cycle: command ``force_N`` ((3,), N, device frame) and return the state.

        The back-end clamps to ``info.limits.max_force_N`` itself as the last line of
        defence. Raises DeviceDisconnected when the device is gone, DeviceError on any other
        I/O failure."""

    def zero(self) -> None:
        """Command zero force (best effort: never raises)."""
        try:
            self.cycle(np.zeros(3))
        except Exception:  # the device may already be gone
            pass

    def _make_safe(self) -> None:
        self.zero()  # close: zero the force, then release the device

    def _open(self) -> None:  # a hook: most back-ends connect here
        pass

    def _close(self) -> None:  # a hook: most back-ends release here
        pass


def clamp_force(force_N: np.ndarray, max_force_N: float) -> tuple[np.ndarray, bool]:
    """(force scaled to at most ``max_force_N`` in magnitude, whether it was). A non-finite
    force becomes zero (and counts as clamped)."""
    f = np.asarray(force_N, dtype=float)
    mag = math.sqrt(float(f @ f)) if f.shape == (3,) else math.nan
    if not math.isfinite(mag):
        return np.zeros(3), True
    if mag > max_force_N:
        return f * (max_force_N / mag), True
    return f, False


def release_after_failed_open(close: Callable[[], None]) -> None:
    """Run a back-end's ``_close`` (a device's or an actuator's) after its ``_open`` raised,
    logging rather than raising its own failure: the open's error is what the user must see."""
    try:
        close()
    except Exception:
        log.warning("releasing a device after a failed open failed too", exc_info=True)
