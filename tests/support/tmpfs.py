"""A small tmpfs mounted for a test: a disk that really fills up (ENOSPC), so the server's full
disk answers are tried against the kernel's own refusal, not a mock.

Mounting needs root (CI runs as root) or CAP_SYS_ADMIN. Where it is not permitted the test is
skipped with the reason, and that skip does not say "(allowed in CI)": with
``BURRFORCE_STRICT_SKIPS=1`` (CI) it fails instead (``tests/conftest.py``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

#: Written in steps of this many bytes when filling a disk.
FILL_STEP = 64 << 10


def mount_unavailable_reason() -> str | None:
    """Why a tmpfs cannot be mounted here, or None."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "mounting a tmpfs needs root (CI runs the tests as root)"
    if shutil.which("mount") is None or shutil.which("umount") is None:
        return "mount/umount are not installed"
    return None


@contextmanager
def small_tmpfs(folder: Path, size: str = "20m") -> Iterator[Path]:
    """``folder`` (made if missing) with a tmpfs of ``size`` mounted on it; unmounted after
    (lazily, should a process still hold a file in it). Skips the test where mounting is not
    permitted."""
    reason = mount_unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0755", "tmpfs",
                           str(folder)], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"mounting a tmpfs is not permitted here: {done.stderr.strip()}")
    try:
        yield folder
    finally:
        if subprocess.run(["umount", str(folder)], capture_output=True).returncode != 0:
            subprocess.run(["umount", "-l", str(folder)], capture_output=True)


def fill(folder: Path, leave_bytes: int = 0, name: str = "filler") -> Path:
    """Fill the disk holding ``folder`` with one file, ``folder/name``, so that
    ``leave_bytes`` (rounded down to whole pages) stay free; returns the file."""
    path = folder / name
    # Unbuffered: a short write takes the last bytes, the next one is refused.
    with open(path, "ab", buffering=0) as f:
        block = bytes(FILL_STEP)
        try:
            while f.write(block):
                pass
        except OSError:
            pass
    if leave_bytes:
        os.truncate(path, max(0, path.stat().st_size - leave_bytes))
    return path


def free_bytes(folder: Path) -> int:
    return shutil.disk_usage(folder).free
