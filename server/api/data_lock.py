"""One server per data directory: the lock ``serve`` takes before it reads anything there.

Two servers on one directory would both resume its journaled sessions, both write their
journals and snapshots, and hand out the same session ids and keys. The lock is an
``flock`` on ``DATA_DIR/serve.lock``, which also holds the holder's PID and addresses (JSON)
so that the second server can name the first. The kernel drops the lock when the holder
exits, however it exits: a crashed server never leaves a stale lock behind.
"""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

LOCK_FILE = "serve.lock"


class DataDirInUse(RuntimeError):
    """Another ``serve`` holds the data directory."""


class DataDirLock:
    """Held from :meth:`acquire` until :meth:`release` or the process's exit."""

    def __init__(self, data_dir: Path) -> None:
        self.path = Path(data_dir).expanduser() / LOCK_FILE
        self._fd: int | None = None

    def acquire(self, http: str = "", udp: str = "") -> None:
        """Take the lock and note this process in it.

        Raises:
            DataDirInUse: another process holds it (the message names it and what to do).
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _describe(_read(fd))
            os.close(fd)
            raise DataDirInUse(
                f"another burrforce serve{holder} is using the data directory "
                f"{self.path.parent}: stop it first, or give this server a directory of its "
                "own with --data-dir") from None
        self._fd = fd
        self.note(http, udp)

    def note(self, http: str = "", udp: str = "") -> None:
        """Record this server's addresses (once its ports are known) for a second one."""
        if self._fd is None:
            return
        text = json.dumps({"pid": os.getpid(), "http": http, "udp": udp}).encode()
        os.ftruncate(self._fd, 0)
        os.pwrite(self._fd, text, 0)

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _read(fd: int) -> dict:
    try:
        data = json.loads(os.pread(fd, 4096, 0) or b"{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _describe(holder: dict) -> str:
    parts = [f"PID {holder['pid']}"] if holder.get("pid") else []
    parts += [f"REST {holder['http']}"] if holder.get("http") else []
    parts += [f"UDP {holder['udp']}"] if holder.get("udp") else []
    return f" ({', '.join(parts)})" if parts else ""
