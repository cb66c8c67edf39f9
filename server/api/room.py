"""How much room the data directory has, and the answers when a write does not fit.

Two limits hold at once: the budget (``ServeConfig.data_budget_bytes``, 0: none), which counts
the user's files (uploads, snapshots, recordings, exports), and the disk that holds the data
directory, which holds whatever it holds. The room left is the smaller of the two; room held
for running recordings (up to their ``max_bytes``, not yet written) is taken from both.

Every refusal says what did not fit, how much it needed (when that is known) and what is free,
and what to do: :func:`no_room` before a write, :func:`disk_filled` when the disk refused one
under way. Raises nothing itself; the errors it builds are ``errors``'.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..whole_files import DiskFull
from .errors import ApiError, NoRoom

#: Folders of the data directory the budget counts, by kind.
COUNTED = ("uploads", "snapshots", "recordings", "exports")
#: Folders reported but not counted.
UNCOUNTED = ("journal",)
#: Where the user looks and what the user deletes, quoted in every refusal for want of room.
WHAT_TO_DELETE = ("GET /v1/storage shows what is stored; DELETE /v1/uploads/ID, "
                  "/v1/snapshots/NAME, /v1/recordings/NAME or /v1/exports/NAME frees it")


def tree_bytes(path: Path) -> tuple[int, int]:
    """(bytes, files) of the regular files under ``path`` (symbolic links are not followed;
    files removed meanwhile, like an export just served, are skipped)."""
    total = files = 0
    todo = [path]
    while todo:
        try:
            entries = os.scandir(todo.pop())
        except (FileNotFoundError, NotADirectoryError):
            continue
        with entries:
            for entry in entries:
                try:
                    if entry.is_dir(follow_symlinks=False):
                        todo.append(Path(entry.path))
                    elif entry.is_file(follow_symlinks=False):
                        total += entry.stat(follow_symlinks=False).st_size
                        files += 1
                except FileNotFoundError:
                    pass
    return total, files


def human_bytes(n: int) -> str:
    """``1536`` → ``1.5 KiB``."""
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(value) < 1024 or unit == "TiB":
            return f"{int(value)} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


@dataclass(frozen=True)
class Usage:
    """The data directory's usage at one moment.

    Attributes:
        bytes_by_kind: bytes per folder (``COUNTED`` and ``UNCOUNTED``).
        items_by_kind: uploads, snapshots, recordings and files (exports, journal) per folder.
        reserved_bytes: room held for running recordings (up to their ``max_bytes``).
        budget_bytes: the budget, 0 for none.
        disk_free_bytes: what the disk holding the data directory has free (None: it cannot
            be measured; then only the budget limits).
    """

    bytes_by_kind: dict[str, int]
    items_by_kind: dict[str, int]
    reserved_bytes: int
    budget_bytes: int
    disk_free_bytes: int | None = None

    @property
    def used_bytes(self) -> int:
        return sum(self.bytes_by_kind[k] for k in COUNTED)

    @property
    def budget_free_bytes(self) -> int | None:
        """Room left under the budget (None: no budget; never negative)."""
        if not self.budget_bytes:
            return None
        return max(0, self.budget_bytes - self.used_bytes - self.reserved_bytes)

    @property
    def disk_room_bytes(self) -> int | None:
        """What the disk has free less what running recordings may still write (None: not
        measured; never negative)."""
        if self.disk_free_bytes is None:
            return None
        return max(0, self.disk_free_bytes - self.reserved_bytes)

    @property
    def free_bytes(self) -> int | None:
        """The room a write has: the smaller of the budget's and the disk's (None: neither
        limits)."""
        rooms = [r for r in (self.budget_free_bytes, self.disk_room_bytes) if r is not None]
        return min(rooms) if rooms else None

    def limited_by(self, incoming_bytes: int = 0) -> str | None:
        """Which limit ``incoming_bytes`` more would break: ``"budget"``, ``"disk"`` or None
        (they fit). 0 asks whether any room is left at all."""
        for name, room in (("budget", self.budget_free_bytes), ("disk", self.disk_room_bytes)):
            if room is not None and (room < incoming_bytes or room == 0):
                return name
        return None

    def fits(self, incoming_bytes: int) -> bool:
        """Whether ``incoming_bytes`` more fit in the budget and on the disk (0: whether the
        files as they are fit: the budget is not exceeded and the disk still has the room
        running recordings hold)."""
        if incoming_bytes == 0:
            return (not self.budget_bytes
                    or self.used_bytes + self.reserved_bytes <= self.budget_bytes) and (
                self.disk_free_bytes is None or self.disk_free_bytes >= self.reserved_bytes)
        return self.limited_by(incoming_bytes) is None


def _held(u: Usage) -> str:
    return (f", {human_bytes(u.reserved_bytes)} held for running recordings"
            if u.reserved_bytes else "")


def over_budget(u: Usage, what: str, error: type[ApiError] = NoRoom,
                incoming_bytes: int = 0) -> ApiError:
    """The answer to a write that does not fit in the budget: the budget, the usage, what to
    delete (``error``: NoRoom, or TooLarge for an upload)."""
    parts = ", ".join(f"{k} {human_bytes(u.bytes_by_kind[k])}" for k in COUNTED)
    size = f" ({human_bytes(incoming_bytes)})" if incoming_bytes else ""
    return error(f"{what}{size} does not fit in the data directory's budget of "
                 f"{human_bytes(u.budget_bytes)} (data_budget_bytes): "
                 f"{human_bytes(u.used_bytes)} is used ({parts}){_held(u)}. {WHAT_TO_DELETE}")


def _disk_advice(data_dir: Path) -> str:
    return (f"Free space on the disk that holds the data directory ({data_dir}), or delete "
            f"what is stored: {WHAT_TO_DELETE}")


def disk_too_full(u: Usage, what: str, data_dir: Path, incoming_bytes: int = 0) -> NoRoom:
    """The answer (507) to a write the disk has no room for, before it is tried."""
    needs = f" needs {human_bytes(incoming_bytes)} but" if incoming_bytes else ""
    return NoRoom(f"{what}{needs} does not fit on the disk: "
                  f"{human_bytes(u.disk_free_bytes or 0)} is free{_held(u)}. "
                  f"{_disk_advice(data_dir)}")


def no_room(u: Usage, what: str, data_dir: Path, error: type[ApiError] = NoRoom,
            incoming_bytes: int = 0) -> ApiError:
    """The answer to a write that breaks a limit (:meth:`Usage.limited_by`): over the budget
    as ``error``, a disk without room always as NoRoom (507)."""
    if u.limited_by(incoming_bytes) == "disk":
        return disk_too_full(u, what, data_dir, incoming_bytes)
    return over_budget(u, what, error, incoming_bytes)


def disk_filled(exc: DiskFull, what: str, data_dir: Path,
                needed_bytes: int | None = None) -> NoRoom:
    """The answer (507) to a write the disk refused under way (nothing of it was kept):
    what it needed (when known; else what had been written) and what is free."""
    if needed_bytes:
        needs = f"needs {human_bytes(needed_bytes)}"
    else:
        needs = f"needs more than the {human_bytes(exc.written_bytes)} written when it filled"
    free = "an unknown amount" if exc.free_bytes is None else human_bytes(exc.free_bytes)
    return NoRoom(f"the disk is full: {what} {needs}, and {free} is free (nothing of it was "
                  f"kept). {_disk_advice(data_dir)}")
