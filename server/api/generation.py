"""Bone generations: a number that names one bone a session holds, new whenever it is replaced.

Bone versions restart at 0 whenever a session's bone is replaced (a new load, a reset, a
restore, a bone rebuilt after a hot-loop restart: every one goes through a load), so a
client's (version) alone cannot tell the new bone from the old one. Each load takes a new
generation; deltas, mesh messages, exports and snapshots say which generation they are of,
and a client whose copy is of another generation is answered with everything (FULL).

Generations are a counter persisted in the data directory (file ``bone-generation``), not
random numbers: they stay small, so JSON readers that hold numbers as doubles (JavaScript
engines, web viewers) keep them exact, and they never repeat while the data directory lives
— also across server restarts and between servers sharing one data directory (the file is
locked while it is bumped). Persisted with fsync before it is handed out, so a crash cannot
hand the same number out twice.

Reading order: a load installs the new reader (``session.reader``) first and its generation
(in ``session.bone_info``) after it. Read the generation *before* the reader
(:func:`bone_generation` first): at worst a newer bone is then labelled with the older
generation, which the client's next request answers with FULL; never an older bone with the
newer generation, which would let the client apply deltas to the wrong base.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Protocol

from ..whole_files import write_whole

try:
    import fcntl
except ImportError:  # Windows: one server per data directory (the thread lock still holds)
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger("burrforce.api")

COUNTER_FILE = "bone-generation"
_lock = threading.Lock()
_last_fallback = 0


class _HasBoneInfo(Protocol):
    bone_info: dict | None


def next_generation(data_dir: Path) -> int:
    """A generation never handed out before from ``data_dir`` (≥ 1). Never raises: a bone
    load must not fail for the counter's sake (see :func:`_fallback`)."""
    path = Path(data_dir) / COUNTER_FILE
    with _lock:
        try:
            with open(path.with_name(COUNTER_FILE + ".lock"), "a+b") as lock:
                if fcntl is not None:
                    fcntl.flock(lock.fileno(), fcntl.LOCK_EX)  # released when closed
                last = _read(path)
                generation = _fallback() if last is None else last + 1
                _write(path, generation)
                return generation
        except OSError as exc:
            generation = _fallback()
            log.warning("the bone generation counter %s cannot be updated (%s): using %d",
                        path, exc, generation)
            return generation


def bone_generation(session: _HasBoneInfo) -> int | None:
    """The generation of the bone ``session`` holds (None before its first load). Read it
    before ``session.reader``: see the module's "Reading order"."""
    info = session.bone_info
    return None if info is None else info.get("generation")


def _read(path: Path) -> int | None:
    """The last generation handed out: 0 for a new data directory, None when the file is
    unreadable (then nobody knows how far the count went)."""
    try:
        text = path.read_text("ascii").strip()
    except FileNotFoundError:
        return 0
    except (OSError, UnicodeDecodeError):
        return None
    if not text.isdigit():
        log.warning("the bone generation counter %s holds %r, not a number", path, text[:40])
        return None
    return int(text)


def _write(path: Path, generation: int) -> None:
    # Whole or not at all, synced with its folder: a crash cannot hand a number out twice,
    # and a full disk leaves no temporary file.
    write_whole(path, f"{generation}\n".encode("ascii"), permissions=0o644)


def _fallback() -> int:
    """A generation when the count is lost or cannot be saved: microseconds since the epoch
    (strictly increasing within the process). That exceeds any count one load at a time could
    have reached (~1.8e15, yet below 2^53, so still exact in JSON); a lost count continues
    from it."""
    global _last_fallback
    _last_fallback = max(time.time_ns() // 1000, _last_fallback + 1)
    return _last_fallback
