"""Back-ends by name, and the ``NAME[:key=value,...]`` specs that choose them.

``burrforce serve --haptic-device falcon:firmware=~/nvent_firmware.bin``, ``--actuator
wav:path=cue.wav`` and the REST attach call all name a back-end and its options this way;
options are the back-end class's keyword arguments (numbers and true/false are converted).
Back-ends are imported only when chosen, so a missing optional package matters only to whoever
asks for its back-end.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass

from .actuators.base import Actuator
from .base import DeviceError, HapticDevice


@dataclass(frozen=True)
class Backend:
    """Attributes: name; kind (``haptic`` or ``actuator``); module and class (lazy); what it
    drives, in a few words; what it needs beyond burrforce's own dependencies."""

    name: str
    kind: str
    module: str
    cls: str
    summary: str
    needs: str = ""
    #: The ``haptics.profiles`` profile of its limits (haptic back-ends); a ``profile``
    #: option overrides it (the sim device's).
    profile: str | None = None

    def profile_for(self, options: dict) -> str | None:
        return str(options.get("profile", self.profile)) if self.kind == "haptic" else None

    def load(self) -> type:
        module = importlib.import_module(self.module, __package__)
        return getattr(module, self.cls)


HAPTIC: dict[str, Backend] = {b.name: b for b in (
    Backend("sim", "haptic", ".sim", "SimDevice",
            "a simulated device (mass, friction, encoder, a scripted hand)", "",
            "generic"),
    Backend("falcon", "haptic", ".falcon.device", "FalconDevice",
            "Novint Falcon over USB (pyusb + libusb, no vendor SDK)",
            "the Falcon's firmware file from Novint's driver or libnifalcon (firmware=PATH), "
            "unless already loaded since power-on", "falcon"),
    Backend("forcedimension", "haptic", ".vendor.forcedimension", "ForceDimensionDevice",
            "Force Dimension omega/delta/sigma/lambda",
            "pip install 'burrforce[forcedimension]' and the Force Dimension SDK", "omega3"),
    Backend("openhaptics", "haptic", ".vendor.openhaptics", "OpenHapticsDevice",
            "3D Systems Touch / Touch X (OpenHaptics HD API)",
            "pip install 'burrforce[openhaptics]', OpenHaptics and the Touch device driver",
            "touch"),
    Backend("haply", "haptic", ".vendor.haply", "HaplyInverse3Device",
            "Haply Inverse3", "pip install 'burrforce[haply]'", "inverse3"),
)}

ACTUATORS: dict[str, Backend] = {b.name: b for b in (
    Backend("audio", "actuator", ".actuators.audio", "AudioActuator",
            "a voice-coil actuator on a sound card (PortAudio)",
            "PortAudio (Debian/Ubuntu: apt-get install libportaudio2)"),
    Backend("usb", "actuator", ".actuators.usb_board", "UsbBoardActuator",
            "burrforce's USB actuator board (docs/actuators.md)"),
    Backend("wav", "actuator", ".actuators.wav", "WavActuator",
            "the waveform written to a WAV file (review, tests)"),
)}


def parse_spec(spec: str) -> tuple[str, dict[str, object]]:
    """``"falcon:index=1,firmware=/x.bin"`` → ``("falcon", {"index": 1, "firmware":
    "/x.bin"})``. Raises ValueError with what is wrong."""
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError("a device spec is NAME or NAME:key=value,key=value")
    name, _, rest = spec.strip().partition(":")
    options: dict[str, object] = {}
    for part in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = part.partition("=")
        key = key.strip()
        if not eq or not key.isidentifier():
            raise ValueError(f"bad option {part!r} in {spec!r}: options are key=value")
        options[key] = _value(value.strip())
    return name.strip(), options


def format_spec(name: str, options: dict[str, object]) -> str:
    """The spec string of ``name`` with ``options`` (the inverse of :func:`parse_spec`)."""
    for key, value in options.items():
        if "," in str(value):
            raise ValueError(f"option {key}={value!r}: a spec's values cannot hold a comma")
    parts = ",".join(f"{k}={str(v).lower() if isinstance(v, bool) else v}"
                     for k, v in options.items())
    return f"{name}:{parts}" if parts else name


#: Options that name files (the wav actuator's output, the Falcon's firmware).
PATH_OPTIONS = ("path", "firmware")


def _value(text: str) -> object:
    lowered = text.lower()
    if lowered in ("true", "yes", "on"):
        return True
    if lowered in ("false", "no", "off"):
        return False
    for convert in (int, float):
        try:
            return convert(text)
        except ValueError:
            pass
    return text


def _construct(table: dict[str, Backend], kind: str, name: str, options: dict) -> object:
    try:
        backend = table[name]
    except KeyError:
        raise ValueError(f"unknown {kind} {name!r}; one of: {', '.join(table)}") from None
    cls = backend.load()
    params = inspect.signature(cls.__init__).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    accepted = [n for n, p in params.items() if n != "self"
                and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    unknown = [k for k in options if k not in accepted]
    if unknown and not takes_any:
        raise ValueError(f"{kind} {name!r} has no option {', '.join(unknown)}; its options: "
                         f"{', '.join(accepted) or 'none'}")
    try:
        return cls(**options)
    except (TypeError, DeviceError) as exc:  # a bad option (a firmware file that is not one)
        raise ValueError(f"{kind} {name!r}: {exc}") from None


def create_device(spec: str) -> HapticDevice:
    """The haptic device a spec names (not opened yet)."""
    name, options = parse_spec(spec)
    return _construct(HAPTIC, "haptic device", name, options)  # type: ignore[return-value]


def create_actuator(spec: str) -> Actuator:
    """The actuator a spec names (not opened yet)."""
    name, options = parse_spec(spec)
    return _construct(ACTUATORS, "actuator", name, options)  # type: ignore[return-value]


def check_spec(spec: str, kind: str) -> tuple[str, dict]:
    """Parse the spec and build the back-end once, to refuse a bad name or option before a
    device process starts (constructors only check their options; ``open`` touches the
    hardware). Raises ValueError with what is wrong."""
    name, options = parse_spec(spec)
    if kind == "haptic":
        create_device(spec)
    else:
        create_actuator(spec)
    return name, options
