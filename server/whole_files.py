"""Files that appear whole or not at all, and a full disk told apart from other failures.

Everything the server keeps or hands out (uploads, snapshots, exports, recordings, the bone
generation counter) is written through :class:`WholeFile`: into a temporary name beside the
target, flushed and ``fsync``-ed, then renamed over the target (and the folder synced, so the
rename survives a power cut). Any failure deletes the temporary file, so a full disk leaves
nothing behind: no 0-byte file, no partial one. A failure for want of room is raised as
:class:`DiskFull`, which says how much had been written and how much the disk has free.

Room for a small file that must be written later whatever happens meanwhile (a recording's
summary once the disk has filled up) is held with :func:`reserve` and used with
:func:`write_reserved`.

This module imports nothing of the server: every room may use it.
"""

from __future__ import annotations

import errno
import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

#: The errnos of a write refused for want of room: no space, or over a disk quota.
DISK_FULL_ERRNOS = frozenset(e for e in (errno.ENOSPC, getattr(errno, "EDQUOT", None))
                             if e is not None)
#: The temporary files :class:`WholeFile` writes end in this (``.NAME.XXXXXXXX.part``).
PART_SUFFIX = ".part"


class DiskFull(OSError):
    """A write the disk had no room for. An ``OSError`` with the original errno.

    Attributes:
        path: the file that was being written (its final name).
        written_bytes: bytes of it written when the disk refused more.
        free_bytes: what the disk had free just after (None: it cannot be measured).
    """

    def __init__(self, cause: OSError, path: Path, written_bytes: int,
                 free_bytes: int | None) -> None:
        super().__init__(cause.errno, cause.strerror or "No space left on device", str(path))
        self.path = path
        self.written_bytes = written_bytes
        self.free_bytes = free_bytes


def is_disk_full(exc: BaseException) -> bool:
    """Whether ``exc`` is a write refused for want of room (ENOSPC or EDQUOT)."""
    return isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS


def disk_free_bytes(path: str | os.PathLike) -> int | None:
    """Bytes free for this process on the file system holding ``path`` (None: it cannot be
    measured, e.g. ``path`` does not exist)."""
    try:
        return shutil.disk_usage(path).free
    except OSError:
        return None


def sync_folder(folder: str | os.PathLike) -> None:
    """``fsync`` a folder, so a rename or a removal in it survives a power cut (a no-op where
    folders cannot be opened, e.g. Windows)."""
    if not hasattr(os, "O_DIRECTORY"):
        return
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class WholeFile:
    """A file written whole or not at all (see the module docstring).

    Use it as a context manager: the block writes to :attr:`file`; leaving it normally
    commits (fsync, rename), leaving it by an exception discards. A caller that must not
    block where the block ends (an event loop) calls :meth:`commit` elsewhere first.

    Args:
        path: the final name; its folder must exist.
        permissions: the file's mode bits (default: 0600, ``mkstemp``'s).
        part_name: a fixed temporary name in the same folder, for a writer that is alone in
            its folder and documents its temporary names (a recording's chunks); default: a
            fresh hidden name, ``.NAME.XXXXXXXX.part``.

    Raises:
        DiskFull: (from the constructor, a write, the commit, or leaving the block) the disk
            had no room; the temporary file is removed.
    """

    def __init__(self, path: str | os.PathLike, permissions: int | None = None,
                 part_name: str | None = None) -> None:
        self.path = Path(path)
        try:
            if part_name is None:
                fd, part = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.",
                                            suffix=PART_SUFFIX)
            else:
                part = str(self.path.with_name(part_name))
                fd = os.open(part, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        except OSError as exc:
            raise self._full(exc, 0) if is_disk_full(exc) else exc from None
        self.part = Path(part)
        self.file: BinaryIO = os.fdopen(fd, "wb")
        self._done = False
        if permissions is not None:
            try:
                os.fchmod(fd, permissions)
            except BaseException:
                self.discard()
                raise

    def write(self, data: bytes | bytearray | memoryview) -> int:
        """Write ``data`` (DiskFull, the file discarded, when it does not fit)."""
        try:
            return self.file.write(data)
        except BaseException as exc:
            self._fail(exc)
            raise

    def commit(self) -> Path:
        """Flush, fsync and rename the file onto its final name; returns it. Once only;
        later calls return the path."""
        if self._done:
            return self.path
        try:
            self.file.flush()
            os.fsync(self.file.fileno())
            self.file.close()
            os.replace(self.part, self.path)
        except BaseException as exc:
            self._fail(exc)
            raise
        self._done = True
        try:
            sync_folder(self.path.parent)
        except OSError:
            pass  # the file is there and whole; only its durability across a power cut is not
        return self.path

    def discard(self) -> None:
        """Remove the temporary file (nothing was written to the final name)."""
        if self._done:
            return
        self._done = True
        try:
            self.file.close()
        except OSError:
            pass  # closing flushes: a full disk refuses that too, and the file goes anyway
        self.part.unlink(missing_ok=True)

    def _full(self, exc: OSError, written: int) -> DiskFull:
        return DiskFull(exc, self.path, written, disk_free_bytes(self.path.parent))

    def _fail(self, exc: BaseException) -> None:
        """Discard after ``exc``; a full disk is raised as DiskFull in its place."""
        if self._done:
            return
        written = 0
        if is_disk_full(exc) and not isinstance(exc, DiskFull):
            try:
                written = self.file.tell()
            except (OSError, ValueError):
                written = 0
        self.discard()
        if is_disk_full(exc) and not isinstance(exc, DiskFull):
            raise self._full(exc, written) from exc  # type: ignore[arg-type]

    def __enter__(self) -> BinaryIO:
        return self.file

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc is None:
            self.commit()
        else:
            self._fail(exc)


def write_whole(path: str | os.PathLike, data: bytes, permissions: int | None = None) -> Path:
    """Replace ``path`` with ``data``, whole or not at all (:class:`WholeFile`)."""
    with WholeFile(path, permissions) as f:
        f.write(data)
    return Path(path)


def reserve(path: str | os.PathLike, size_bytes: int) -> Path:
    """Hold ``size_bytes`` of the disk in a file at ``path`` (zeros, written and synced, so
    the room is taken now, on every file system), for :func:`write_reserved` later."""
    path = Path(path)
    with WholeFile(path) as f:
        f.write(bytes(size_bytes))
    return path


def write_reserved(reserved: str | os.PathLike, path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` (at most the reserved size) to ``path`` in the room :func:`reserve`
    held at ``reserved``: written over the reserved bytes in place (no new blocks on file
    systems that overwrite in place: ext4, XFS, tmpfs), cut to length, synced, then renamed
    onto ``path``, so ``path`` appears whole. Where that fails for want of room (a
    copy-on-write file system), or ``data`` is larger than the room held, the room is given
    back and ``path`` written the usual way. A file ``path`` held before is replaced either
    way."""
    reserved, path = Path(reserved), Path(path)
    if len(data) > reserved.stat().st_size:  # more than was held: the usual way
        reserved.unlink()
        return write_whole(path, data)
    try:
        with open(reserved, "r+b") as f:
            f.write(data)
            f.truncate(len(data))
            f.flush()
            os.fsync(f.fileno())
        os.replace(reserved, path)
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        reserved.unlink(missing_ok=True)
        return write_whole(path, data)
    try:
        sync_folder(path.parent)
    except OSError:
        pass
    return path
