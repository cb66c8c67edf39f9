"""The connection file: where a running ``burrforce serve`` can be reached, and with what key.

``serve`` writes it (mode 0600) when its port is open and removes it when it stops; the
client's commands read it when no endpoint or key is given, so on one machine
``burrforce serve`` in one terminal and ``burrforce client demo`` in another just work.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

ENV_VAR = "BURRFORCE_CONNECTION"


@dataclass(frozen=True)
class Connection:
    """A session's endpoint: UDP host and port, session id, key (hex, or None), frame, the
    bone's voxel size (mm) when known, and the REST control plane's URL and bearer token."""

    host: str
    udp_port: int
    session: int
    key_hex: str | None
    frame: str
    voxel_mm: float | None = None
    http_url: str | None = None
    token: str | None = None


def default_path() -> Path:
    """$BURRFORCE_CONNECTION, else $XDG_RUNTIME_DIR/burrforce/connection.json, else
    ~/.cache/burrforce/connection.json."""
    if os.environ.get(ENV_VAR):
        return Path(os.environ[ENV_VAR])
    runtime = os.environ.get("XDG_RUNTIME_DIR")
    base = Path(runtime) if runtime else Path.home() / ".cache"
    return base / "burrforce" / "connection.json"


def write(connection: Connection, path: Path | None = None) -> Path:
    """Write atomically, readable by this user only (it holds the session key and the REST
    token)."""
    path = path or default_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        json.dump(asdict(connection), f, indent=2)
        f.write("\n")
    os.replace(tmp, path)
    return path


def read(path: Path | None = None) -> Connection:
    """The connection a running server wrote.

    Raises:
        ValueError: no such file (no server running, or another path), or not a connection
            file.
    """
    path = path or default_path()
    try:
        data = json.loads(path.read_text())
        return Connection(str(data["host"]), int(data["udp_port"]), int(data["session"]),
                          None if data["key_hex"] is None else str(data["key_hex"]),
                          str(data["frame"]),
                          None if data.get("voxel_mm") is None else float(data["voxel_mm"]),
                          None if data.get("http_url") is None else str(data["http_url"]),
                          None if data.get("token") is None else str(data["token"]))
    except FileNotFoundError:
        raise ValueError(f"no connection file at {path}: is `burrforce serve` running? "
                         "(or give --server, --session and --key)") from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path} is not a burrforce connection file: {exc}") from None


def remove(path: Path | None = None, only_if: Connection | None = None) -> None:
    """Remove the file (if it still describes ``only_if``: another server may own it now)."""
    path = path or default_path()
    try:
        if only_if is not None and read(path) != only_if:
            return
        path.unlink()
    except (OSError, ValueError):
        pass
