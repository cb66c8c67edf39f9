"""The server's configuration: defaults, then a TOML file, then the environment, then flags.

TOML (``burrforce serve --config FILE``)::

    [server]
    host = "127.0.0.1"          # the REST and UDP address
    http_port = 47811
    udp_port = 47810
    token = "..."               # the REST bearer token; default: generated, shown once
    data_dir = "~/.local/share/burrforce"   # uploads, snapshots, recordings
    bone_library = "/srv/bones" # bones sessions may load by name (library:NAME)
    upload_max_mb = 1024
    data_budget_bytes = "20GiB" # uploads + snapshots + recordings + exports; 0: no limit
    load_budget_bytes = 0       # memory one bone load may take; 0: its bone's + 512 MiB
    cors_origins = []           # browser origins allowed to call the API (default none)
    max_sessions = 16           # sessions held at once (each keeps its bone in memory)
    workers = 3                 # hot-loop processes, worker i on udp_port + i (serve's
                                # default: one per core less one)
    wake_ahead_us = 250         # poll from this long before a stream's next packet; 0: off
    wake_cpu_share = 0.4        # ...while a loop is awake less than this share of a core
    realtime = false            # hot loops under SCHED_FIFO (needs CAP_SYS_NICE or rtprio)

    [session]                   # the default session serve starts with
    bone = "phantom:temporal"
    voxel_mm = 0.2
    frame = "unity"
    device = "touch"            # the haptic device the force is for: coupled output

Environment variables: ``BURRFORCE_`` + the key in upper case (``BURRFORCE_HTTP_PORT=8080``,
``BURRFORCE_TOKEN=…``, ``BURRFORCE_BONE=phantom:workpiece``); lists are comma-separated.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

from ..haptics.profiles import PROFILES
from ..hotloop.wake import DEFAULT_CPU_SHARE, DEFAULT_LEAD_US, WakeConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

DEFAULT_HTTP_PORT = 47811
DEFAULT_UDP_PORT = 47810
ENV_PREFIX = "BURRFORCE_"
#: The REST token's file in the data directory (mode 0600), made at the first start.
TOKEN_FILE = "token"


def is_loopback(host: str) -> bool:
    """Whether ``host`` is reachable from this machine only (keyless sessions are for it)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def default_data_dir() -> Path:
    base = os.environ.get("XDG_DATA_HOME") or Path.home() / ".local" / "share"
    return Path(base) / "burrforce"


@dataclass(frozen=True)
class ServeConfig:
    """Everything ``burrforce serve`` needs (see the module docstring for where it comes from).

    Attributes:
        host: address for both REST and UDP. 127.0.0.1 keeps the server on this machine.
        http_port, udp_port: ports (0: any free one).
        token: the REST bearer token; None generates one at start and prints it once.
        data_dir: uploads, snapshots and recordings live under it.
        bone_library: a folder of bone files sessions may load as ``library:NAME``.
        upload_max_mb: the largest bone upload accepted, MB.
        data_budget_bytes: what uploads, snapshots, recordings and exports may take together
            (``GET /v1/storage``); writes beyond it are refused. 0: no limit. TOML and the
            environment also take sizes like ``"20GiB"`` or ``"500M"``.
        load_budget_bytes: the most memory loading one bone may take in the control plane,
            bytes (sizes as for ``data_budget_bytes``): a file whose bone would need more is
            refused (413) from its header, before a voxel is read. 0: each load's own
            budget, the bone's bytes (3 per voxel) plus 512 MiB — the source is read and
            converted a slab at a time, never whole, so that is room enough.
        cors_origins: browser origins allowed to call the API; empty turns CORS off.
        max_sessions: sessions the server holds at once (each keeps its bone in memory).
        workers: hot-loop processes; worker i listens on ``udp_port + i``, each session runs
            on one of them for life. None: one (``burrforce serve`` picks
            ``hotloop.pool.default_workers()``).
        wake_ahead_us, wake_cpu_share: each hot loop wakes this long before its streams'
            predicted packets and polls for them, while it is awake less than this share of
            a core (``hotloop.wake``); a lead of 0 blocks until each datagram arrives.
        realtime: each hot loop's loop thread asks for SCHED_FIFO
            (``server.realtime``) and blocks for each datagram instead of
            waking ahead; where that is not permitted it runs as without (``/v1/health`` says
            per worker).
        bone, voxel_mm, frame: the default session's bone and engine frame.
        device: the haptic device profile of the default session (``haptics.PROFILE_NAMES``):
            its output is then coupled. None: no device, the raw force.
        session_id: the default session's id.
        key: the default session's key in hex; None makes a fresh one. ``no_auth`` drops it
            (loopback development only).
    """

    host: str = "127.0.0.1"
    http_port: int = DEFAULT_HTTP_PORT
    udp_port: int = DEFAULT_UDP_PORT
    token: str | None = None
    data_dir: Path = field(default_factory=default_data_dir)
    bone_library: Path | None = None
    upload_max_mb: float = 1024.0
    data_budget_bytes: int = 20 << 30
    load_budget_bytes: int = 0
    cors_origins: tuple[str, ...] = ()
    max_sessions: int = 16
    workers: int | None = None
    wake_ahead_us: float = DEFAULT_LEAD_US
    wake_cpu_share: float = DEFAULT_CPU_SHARE
    realtime: bool = False
    bone: str = "phantom:temporal"
    voxel_mm: float | None = None
    frame: str = "si_mm"
    device: str | None = None
    session_id: int = 1
    key: str | None = None
    no_auth: bool = False

    def __post_init__(self) -> None:
        for name in ("http_port", "udp_port"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 65535:
                raise ValueError(f"{name} must be a port number 0..65535, got {value!r}")
        if isinstance(self.max_sessions, bool) or not isinstance(self.max_sessions, int) \
                or self.max_sessions < 1:
            raise ValueError(f"max_sessions must be a positive integer, got "
                             f"{self.max_sessions!r}")
        if self.workers is not None:
            if isinstance(self.workers, bool) or not isinstance(self.workers, int) \
                    or self.workers < 1:
                raise ValueError(f"workers must be an integer ≥ 1 (hot-loop processes), got "
                                 f"{self.workers!r}")
            if self.udp_port and self.udp_port + self.workers - 1 > 65535:
                raise ValueError(f"{self.workers} workers need UDP ports {self.udp_port}.."
                                 f"{self.udp_port + self.workers - 1}: past 65535")
        WakeConfig(self.wake_ahead_us, self.wake_cpu_share)  # raises what is wrong with them
        if not (isinstance(self.upload_max_mb, (int, float)) and
                math.isfinite(self.upload_max_mb) and self.upload_max_mb > 0):
            raise ValueError(f"upload_max_mb must be a positive number, got "
                             f"{self.upload_max_mb!r}")
        if isinstance(self.data_budget_bytes, bool) or not isinstance(
                self.data_budget_bytes, int) or self.data_budget_bytes < 0:
            raise ValueError(f"data_budget_bytes must be a non-negative integer (0: no "
                             f"limit), got {self.data_budget_bytes!r}")
        if isinstance(self.load_budget_bytes, bool) or not isinstance(
                self.load_budget_bytes, int) or self.load_budget_bytes < 0:
            raise ValueError(f"load_budget_bytes must be a non-negative integer (0: the "
                             f"bone's bytes + 512 MiB), got {self.load_budget_bytes!r}")
        if self.device is not None and self.device not in PROFILES:
            raise ValueError(f"device must be one of {', '.join(PROFILES)}, got "
                             f"{self.device!r}")
        if self.token is not None and len(self.token) < 16:
            raise ValueError("token must be at least 16 characters (a guessable token is no "
                             "protection)")

    @property
    def worker_count(self) -> int:
        """How many hot loops to start (``workers``, None: one)."""
        return 1 if self.workers is None else self.workers

    @property
    def wake(self) -> WakeConfig:
        """The hot loops' waking ahead (raises ValueError for a bad lead or share)."""
        return WakeConfig(self.wake_ahead_us, self.wake_cpu_share)

    @property
    def upload_max_bytes(self) -> int:
        return int(self.upload_max_mb * (1 << 20))


_TYPES = {f.name: f.type for f in fields(ServeConfig)}
_KEYS = {"server": ("host", "http_port", "udp_port", "token", "data_dir", "bone_library",
                    "upload_max_mb", "data_budget_bytes", "load_budget_bytes", "cors_origins",
                    "max_sessions",
                    "workers", "wake_ahead_us", "wake_cpu_share", "realtime"),
         "session": ("bone", "voxel_mm", "frame", "device", "session_id", "key",
                     "no_auth")}


def _coerce(name: str, value: object, source: str) -> object:
    """A TOML or environment value as the field's type; ValueError names where it came from."""
    kind = _TYPES[name]
    if name in ("data_budget_bytes", "load_budget_bytes") and value is not None:
        try:
            return parse_size_bytes(value)  # type: ignore[arg-type]
        except ValueError as exc:
            raise ValueError(f"{source}: {name}: {exc}") from None
    try:
        if value is None:
            return None
        if "int" in kind and "float" not in kind:
            if isinstance(value, bool):
                raise ValueError
            return int(value)  # type: ignore[arg-type]
        if "float" in kind:
            if isinstance(value, bool):
                raise ValueError
            return float(value)  # type: ignore[arg-type]
        if "bool" in kind:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if "Path" in kind:
            return Path(str(value)).expanduser()
        if "tuple" in kind:
            items = value.split(",") if isinstance(value, str) else value
            if not isinstance(items, (list, tuple)):
                raise ValueError
            return tuple(str(x).strip() for x in items if str(x).strip())
        if not isinstance(value, str):
            raise ValueError
        return value
    except (TypeError, ValueError):
        raise ValueError(f"{source}: {name} has the wrong type ({value!r})") from None


_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*(?:([kmgt])(?:i?b)?|b)?\s*$", re.IGNORECASE)


def parse_size_bytes(value: str | int) -> int:
    """A size in bytes from ``20GiB``, ``20G``, ``500MB``, ``1.5T`` or a plain number.
    K, M, G, T are binary (1024-based) with or without ``iB``/``B``: a budget is about
    disk space, which tools report that way. Raises ValueError saying what was wrong."""
    if isinstance(value, bool):
        raise ValueError(f"not a size: {value!r}")
    if isinstance(value, int):
        if value < 0:
            raise ValueError(f"a size cannot be negative: {value}")
        return value
    match = _SIZE.match(str(value))
    if match is None:
        raise ValueError(f"not a size: {value!r} (e.g. 20GiB, 500M, 0)")
    number, unit = match.groups()
    return int(float(number) * (1 << (10 * " KMGT".index((unit or " ").upper()))))


def from_toml(path: Path, base: ServeConfig | None = None) -> ServeConfig:
    """``base`` (default: the defaults) with what the TOML file sets."""
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise ValueError(f"cannot read the config file {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path} is not valid TOML: {exc}") from None
    changes: dict[str, object] = {}
    for table, value in data.items():
        if table not in _KEYS or not isinstance(value, dict):
            raise ValueError(f"{path}: unknown table [{table}] (known: "
                             f"{', '.join(_KEYS)})")
        for key, item in value.items():
            if key not in _KEYS[table]:
                raise ValueError(f"{path}: unknown key {key!r} in [{table}] (known: "
                                 f"{', '.join(_KEYS[table])})")
            changes[key] = _coerce(key, item, str(path))
    return replace(base or ServeConfig(), **changes)  # type: ignore[arg-type]


def from_environment(base: ServeConfig, environ: Mapping[str, str] | None = None
                     ) -> ServeConfig:
    """``base`` with what ``BURRFORCE_*`` variables set."""
    environ = os.environ if environ is None else environ
    changes = {}
    for name in _TYPES:
        value = environ.get(ENV_PREFIX + name.upper())
        if value is not None and value != "":
            changes[name] = _coerce(name, value, ENV_PREFIX + name.upper())
    return replace(base, **changes)  # type: ignore[arg-type]


def load_config(path: Path | None = None, flags: Mapping[str, object] | None = None,
                environ: Mapping[str, str] | None = None) -> ServeConfig:
    """Defaults ← the TOML file ← the environment ← flags (those not None)."""
    config = from_toml(path) if path is not None else ServeConfig()
    config = from_environment(config, environ)
    changes = {k: v for k, v in (flags or {}).items() if v is not None and k in _TYPES}
    return replace(config, **changes)  # type: ignore[arg-type]
