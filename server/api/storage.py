"""The data directory as the user sees it: what is stored (uploads, snapshots, recordings and
the exports being served), how much room it takes and has, writing into it within that room,
and deleting from it safely. :class:`Storage` is the only code that lists, sizes or deletes
these files.

The budget (``ServeConfig.data_budget_bytes``, 0: none) counts every file under uploads/,
snapshots/, recordings/ and exports/; the journal (data_dir/journal) is reported but not
counted, since the server needs it whatever the user keeps. The disk that holds the data
directory limits too: the room left is the smaller of the two (``room``). A running recording
holds room up to its ``max_bytes`` (reserved): it was capped by the room left when it started,
so it stops cleanly there instead of filling the disk, and other writes cannot take that room
from it.

Every file is written whole or not at all (``whole_files.WholeFile``): a write the disk
refuses under way is answered 507 (NoRoom) and leaves nothing behind. Temporary files of a
server that was killed mid-write, and exports it never finished serving, are removed when the
next one starts (:meth:`Storage.remove_leftovers`).

Names from URLs are resolved here and only here: a name is one plain path component of the
kind's form (an upload id, a snapshot or recording name), never ``..``, a slash, an absolute
path or a NUL, so nothing outside the kind's folder can be listed, read or deleted.

Raises the domain errors of ``errors`` (BadName, NotFound, Conflict, NoRoom, TooLarge).
"""

from __future__ import annotations

import asyncio
import logging
import re
import secrets
import shutil
import time
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO

from ..bone import Bone
from ..bone.loaders import write_bone
from ..whole_files import DiskFull, WholeFile, disk_free_bytes
from .archive import Archive, tar_archive
from .errors import ApiError, BadName, Conflict, Invalid, NoRoom, NotFound, TooLarge
from .jobs import JobTable
from .room import COUNTED, UNCOUNTED, Usage, disk_filled, no_room, tree_bytes
from .sessions import SessionTable
from .sources import SNAPSHOT_SUFFIX, UPLOAD_ID, SourceError, SourceRoots, snapshot_path

log = logging.getLogger("burrforce.api")

RECORDING_SUFFIX = ".burrrec"
RECORDING_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
#: Room a recording needs beyond its chunk files (which ``max_bytes`` bounds): meta, start
#: patch and summary, all small.
RECORDING_MARGIN_BYTES = 64 << 10
EXPORT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,120}$")
#: Temporary files of writes under way (``WholeFile``'s ``.NAME.XXXX.part``; older servers'
#: ``.upload-*``, ``.burrforce-*.tmp`` and ``.bone-generation.PID.tmp``): a server that
#: starts removes those a killed one left.
LEFTOVER = re.compile(r"^\.(.+\.part|upload-.*|burrforce-.*\.tmp|bone-generation\..*\.tmp)$")


def _items(kind: str, folder: Path, files: int) -> int:
    if kind == "uploads":
        return len(_upload_files(folder))
    if kind == "snapshots":
        return sum(1 for _ in folder.glob("*" + SNAPSHOT_SUFFIX))
    if kind == "recordings":
        return sum(1 for p in folder.glob("*" + RECORDING_SUFFIX) if p.is_dir())
    return files


# -- names --------------------------------------------------------------------------------------
def plain_name(name: str, what: str) -> str:
    """``name`` if it is one plain path component; BadName for traversal, absolute paths,
    NUL."""
    if not name or "\x00" in name or "/" in name or "\\" in name or ".." in name \
            or name.startswith("."):
        raise BadName(f"{what} name {name!r} must be a plain name of letters, digits, "
                      "'_', '-', '.': no '/', '\\', '..', leading '.' or NUL")
    return name


def _inside(folder: Path, path: Path, what: str, name: str) -> Path:
    # A symbolic link planted in the folder must not lead a delete or download elsewhere.
    if path.is_symlink() or folder.resolve() != path.resolve().parent:
        raise BadName(f"{what} {name!r} is not in the {what}s folder")
    return path


def _upload_files(folder: Path) -> list[Path]:
    # Uploads in flight are ``.upload-*`` temporaries: not an upload yet.
    return sorted(p for p in folder.glob("*.*") if not p.name.startswith(".")
                  and UPLOAD_ID.match(p.name.split(".", 1)[0]))


def snapshot_entry(path: Path) -> dict:
    name = path.name[: -len(SNAPSHOT_SUFFIX)]
    return {"name": name, "source": f"snapshot:{name}", "bytes": path.stat().st_size,
            "created": path.stat().st_mtime}


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def _deleted(kind: str, name: str, size: int, users: list[int],
             source: str | None) -> dict:
    answer: dict = {"deleted": name, "kind": kind, "bytes": size, "in_use_by": users,
                    "note": None}
    if users:
        # The bone is in the sessions' memory already; only reloading it needs the file.
        answer["note"] = (f"session{'s' if len(users) > 1 else ''} "
                          f"{', '.join(map(str, users))} loaded {source} and keep"
                          f"{'' if len(users) > 1 else 's'} its bone, but a reset will fail "
                          "and, after a crash or restart, the session cannot be resumed from "
                          "its journal: the file is gone")
    return answer


class Storage:
    """The data directory's user files: uploads, snapshots, recordings, exports; thread-safe
    (it holds no state but the budget; the files and the tables it reads are the truth).

    Args:
        data_dir: the data directory (its kind folders are made here).
        library: the bone library (``library:`` sources), or None.
        budget_bytes: the budget, 0 for none.
        sessions: the sessions (whose bone came from which file, who records where).
        jobs: the bone loads (a file being read is not deleted).
    """

    def __init__(self, data_dir: Path, library: Path | None, budget_bytes: int,
                 sessions: SessionTable, jobs: JobTable) -> None:
        self.data_dir = Path(data_dir).expanduser()
        self.roots = SourceRoots(library, self.data_dir / "uploads",
                                 self.data_dir / "snapshots")
        self.recordings_dir = self.data_dir / "recordings"
        self.exports_dir = self.data_dir / "exports"
        for d in (self.roots.uploads, self.roots.snapshots, self.recordings_dir,
                  self.exports_dir):
            d.mkdir(parents=True, exist_ok=True)
        self.budget_bytes = int(budget_bytes)
        self.sessions = sessions
        self.jobs = jobs
        self.remove_leftovers()

    def remove_leftovers(self) -> list[Path]:
        """Remove what a server killed mid-write left: temporary files (``LEFTOVER``) in the
        data directory and its kind folders, and every export (an export is served once,
        and no server serves those of the one before). Call at start, before any write;
        returns what was removed."""
        removed: list[Path] = []
        for folder in (self.data_dir, self.roots.uploads, self.roots.snapshots,
                       self.recordings_dir, self.exports_dir):
            for path in folder.iterdir():
                if (folder == self.exports_dir or LEFTOVER.match(path.name)) \
                        and not path.is_symlink() and path.is_file():
                    path.unlink(missing_ok=True)
                    removed.append(path)
        if removed:
            log.info("removed %d file(s) a stopped server left unfinished: %s", len(removed),
                     ", ".join(str(p.relative_to(self.data_dir)) for p in removed[:10]))
        return removed

    # -- usage ------------------------------------------------------------------------------
    def measure(self) -> Usage:
        """What the data directory holds now, what running recordings may still add, and
        what the disk has free."""
        sizes: dict[str, int] = {}
        items: dict[str, int] = {}
        for kind in COUNTED + UNCOUNTED:
            folder = self.data_dir / kind
            sizes[kind], files = tree_bytes(folder)
            items[kind] = _items(kind, folder, files) if folder.is_dir() else 0
        return Usage(sizes, items, self._reserved_bytes(), self.budget_bytes,
                     disk_free_bytes(self.data_dir))

    def _running_recordings(self) -> list[tuple[int, dict]]:
        return [(s.id, rec) for s in self.sessions.values()
                if (rec := s.recording) is not None]

    def _reserved_bytes(self) -> int:
        reserved = 0
        for _, rec in self._running_recordings():
            cap = rec.get("max_bytes")
            if cap is None:
                continue
            written = sum(p.stat().st_size for p in Path(rec["path"]).glob("chunk-*")
                          if p.is_file())
            reserved += max(0, int(cap) - written)
        return reserved

    def report(self) -> dict:
        """``GET /v1/storage``: usage per kind, the budget, what is left (the smaller of the
        budget's room and the disk's)."""
        u = self.measure()
        kinds = {kind: {"bytes": u.bytes_by_kind[kind], "items": u.items_by_kind[kind],
                        "counted": kind in COUNTED} for kind in COUNTED + UNCOUNTED}
        for kind in ("uploads", "snapshots", "recordings", "exports"):
            kinds[kind]["list"] = f"/v1/{kind}"
        return {"data_dir": str(self.data_dir), "budget_bytes": u.budget_bytes,
                "used_bytes": u.used_bytes, "reserved_bytes": u.reserved_bytes,
                "free_bytes": u.free_bytes, "disk_free_bytes": u.disk_free_bytes,
                "kinds": kinds}

    def require_room(self, what: str, error: type[ApiError] = NoRoom,
                     incoming_bytes: int = 0) -> Usage:
        """Raise unless ``incoming_bytes`` more fit in the budget and on the disk; with no
        size known (0), unless some room is left at all: ``error`` over the budget, NoRoom
        on a full disk. Returns the usage measured."""
        u = self.measure()
        if u.limited_by(incoming_bytes) is not None:
            raise no_room(u, what, self.data_dir, error, incoming_bytes)
        return u

    def check_written(self, path: Path, what: str) -> None:
        """After writing ``path`` (whose size was unknown beforehand): if it took the data
        directory over the budget, or the disk below the room running recordings hold,
        remove it and raise NoRoom."""
        u = self.measure()
        if u.fits(0):
            return
        size = tree_bytes(path)[0] if path.is_dir() else path.stat().st_size
        _remove(path)
        raise no_room(self.measure(), what, self.data_dir, NoRoom, size)

    def recording_cap(self, max_bytes: int) -> int:
        """``max_bytes`` capped by the room left in the budget and on the disk (measured
        after the recording's start snapshot was written); NoRoom when nothing is left."""
        u = self.measure()
        if u.free_bytes is None:
            return max_bytes
        room = u.free_bytes - RECORDING_MARGIN_BYTES
        if room <= 0:
            raise no_room(u, "a recording", self.data_dir, NoRoom,
                          RECORDING_MARGIN_BYTES + 1)
        return min(max_bytes, room)

    def disk_filled(self, exc: DiskFull, what: str,
                    needed_bytes: int | None = None) -> NoRoom:
        """The answer (507) to a write of ``what`` the disk refused under way."""
        return disk_filled(exc, what, self.data_dir, needed_bytes)

    # -- writing ----------------------------------------------------------------------------
    @contextmanager
    def writing(self, path: Path, what: str, needed_bytes: int | None = None
                ) -> Iterator[BinaryIO]:
        """Write ``path`` whole or not at all: checks the room first (``needed_bytes`` if
        known), yields the open temporary file, then checks the room taken (NoRoom, and
        nothing kept, when the disk refuses the write or the file broke a limit)."""
        self.require_room(what, incoming_bytes=needed_bytes or 0)
        try:
            with WholeFile(path) as f:
                yield f
        except DiskFull as exc:
            raise self.disk_filled(exc, what, needed_bytes) from None
        self.check_written(path, what)

    def save_snapshot(self, bone: Bone, name: str | None, session_id: int,
                      generation: int | None) -> dict:
        """Save ``bone`` (session ``session_id``'s, of bone ``generation``) as snapshot
        ``name`` (None: one named after the session, version and time). Conflict if it
        exists; NoRoom when it does not fit (the budget, the disk)."""
        if name is None:
            name = (f"session-{session_id}-v{bone.grid.version}-"
                    f"{time.strftime('%Y%m%d-%H%M%S')}")
        try:
            path = snapshot_path(self.roots.snapshots, name)
        except SourceError as exc:
            raise exc.as_api_error() from None
        if path.exists():
            raise Conflict(f"snapshot {name!r} exists")
        with self.writing(path, "the snapshot") as f:
            write_bone(bone, f, generation)
        return snapshot_entry(path)

    def new_recording_dir(self, name: str) -> Path:
        """An empty folder for recording ``name`` (``.burrrec`` added if missing); Conflict
        if it exists, NoRoom when the budget or the disk is full."""
        path = self.recordings_dir / (name if name.endswith(RECORDING_SUFFIX)
                                      else name + RECORDING_SUFFIX)
        if path.exists():
            raise Conflict(f"recording {path.name} exists")
        self.require_room("a recording")
        path.mkdir(parents=True)
        return path

    async def receive_upload(self, chunks: AsyncIterator[bytes], suffix: str,
                             limit_bytes: int, declared_bytes: int | None) -> tuple[str, int]:
        """Store an upload as it streams in, whole or not at all; returns its id and size.
        TooLarge past ``limit_bytes`` or the budget, NoRoom when the disk has no room for it,
        Invalid when it is empty."""
        # Walking the data directory takes a while with many recordings: not on the event
        # loop.
        usage = await asyncio.to_thread(self.require_room, "the upload", TooLarge,
                                        declared_bytes or 0)
        upload_id = secrets.token_hex(8)
        size = 0
        try:
            part = WholeFile(self.roots.uploads / (upload_id + suffix))
            with part as f:
                async for chunk in chunks:
                    size += len(chunk)
                    if size > limit_bytes:
                        raise TooLarge(f"the upload exceeds the limit of {limit_bytes:,} bytes "
                                       "(serve's upload_max_mb)")
                    if not usage.fits(size):
                        raise no_room(usage, "the upload", self.data_dir, TooLarge, size)
                    f.write(chunk)
                if size == 0:
                    raise Invalid("the upload is empty")
                await asyncio.to_thread(part.commit)  # fsync: not on the event loop
        except DiskFull as exc:
            raise self.disk_filled(exc, "the upload", declared_bytes) from None
        return upload_id, size

    def write_export(self, suffix: str, write: Callable[[BinaryIO], object],
                     needed_bytes: int | None = None) -> Path:
        """A new file in exports/ ending in ``suffix``, written by ``write(file)`` whole or
        not at all (:meth:`writing`); the caller serves it, then deletes it."""
        path = self.exports_dir / f"export-{secrets.token_hex(8)}{suffix}"
        with self.writing(path, "the export", needed_bytes) as f:
            write(f)
        return path

    # -- names ------------------------------------------------------------------------------
    def upload_file(self, upload_id: str) -> Path:
        """The stored file of upload ``upload_id`` (``ID`` or ``upload:ID``)."""
        upload_id = plain_name(upload_id.removeprefix("upload:"), "upload")
        if not UPLOAD_ID.match(upload_id):
            raise BadName(f"upload id {upload_id!r} is not one this server issues "
                          "(16 hex digits)")
        matches = sorted(self.roots.uploads.glob(upload_id + ".*"))
        if not matches:
            raise NotFound(f"no upload {upload_id}")
        return _inside(self.roots.uploads, matches[0], "upload", upload_id)

    def snapshot_file(self, name: str) -> Path:
        """The file of snapshot ``name`` (``NAME``, ``NAME.bone.npz`` or ``snapshot:NAME``)."""
        name = plain_name(name.removeprefix("snapshot:"), "snapshot")
        try:
            path = snapshot_path(self.roots.snapshots, name)
        except SourceError as exc:
            raise exc.as_api_error() from None
        if not path.is_file():
            raise NotFound(f"no snapshot {name!r}")
        return _inside(self.roots.snapshots, path, "snapshot", name)

    def recording_dir(self, name: str) -> Path:
        """The directory of recording ``name`` (with or without ``.burrrec``)."""
        plain_name(name, "recording")
        if not RECORDING_NAME.match(name):
            raise BadName(f"recording name {name!r}: letters, digits, '_', '-', '.' only")
        if not name.endswith(RECORDING_SUFFIX):
            name += RECORDING_SUFFIX
        path = self.recordings_dir / name
        if not path.is_dir():
            raise NotFound(f"no recording {name!r}")
        return _inside(self.recordings_dir, path, "recording", name)

    # -- listing ----------------------------------------------------------------------------
    def sessions_from(self, path: Path) -> list[int]:
        """Sessions whose bone was loaded from ``path``."""
        target = path.resolve()
        return sorted(s.id for s in self.sessions.values()
                      if s.source.path is not None and Path(s.source.path).resolve() == target)

    def list_uploads(self) -> list[dict]:
        out = []
        for path in _upload_files(self.roots.uploads):
            upload_id = path.name.split(".", 1)[0]
            st = path.stat()
            out.append({"id": upload_id, "source": f"upload:{upload_id}", "file": path.name,
                        "bytes": st.st_size, "created": st.st_mtime,
                        "in_use_by": self.sessions_from(path)})
        return out

    def list_snapshots(self) -> list[dict]:
        return [{**snapshot_entry(p), "in_use_by": self.sessions_from(p)}
                for p in sorted(self.roots.snapshots.glob("*" + SNAPSHOT_SUFFIX))]

    def _writer(self, path: Path) -> int | None:
        """The session writing recording ``path``, if one is."""
        target = path.resolve()
        for session_id, rec in self._running_recordings():
            if Path(rec["path"]).resolve() == target:
                return session_id
        return None

    def list_recordings(self) -> list[dict]:
        out = []
        for path in sorted(self.recordings_dir.glob("*" + RECORDING_SUFFIX)):
            if not path.is_dir():
                continue
            size, files = tree_bytes(path)
            mtimes = [p.stat().st_mtime for p in path.iterdir() if p.is_file()]
            meta = path / "meta.json"
            out.append({"name": path.name, "bytes": size, "files": files,
                        "created": meta.stat().st_mtime if meta.exists()
                        else path.stat().st_mtime,
                        "modified": max(mtimes, default=path.stat().st_mtime),
                        "complete": (path / "summary.json").exists(),
                        "recording_session": self._writer(path),
                        "replay": f"burrforce replay {path}"})
        return out

    # -- deleting and downloading -----------------------------------------------------------
    def _delete_bone_file(self, kind: str, name: str, path: Path, sources: set[str],
                          force: bool = False) -> dict:
        jobs = self.jobs.loading(sources)
        if jobs:
            raise Conflict(f"{kind} {name!r} is being loaded (job {', '.join(jobs)}): "
                           "delete it once the load is done")
        users = self.sessions_from(path)
        if users and not force:
            # Their bone is in memory, but a reset reloads the file, and so does resuming
            # them from the journal after a crash: deleting it is the user's call, made
            # knowingly.
            raise Conflict(f"{kind} {name!r} is the bone of session"
                           f"{'s' if len(users) > 1 else ''} {', '.join(map(str, users))}: "
                           "a reset, and resuming after a crash or restart, need it. Delete "
                           "those sessions first, or add ?force=true to delete it anyway")
        size = path.stat().st_size
        path.unlink(missing_ok=True)
        return _deleted(kind, name, size, users, sorted(sources)[0])

    def delete_upload(self, upload_id: str, force: bool = False) -> dict:
        path = self.upload_file(upload_id)
        upload_id = path.name.split(".", 1)[0]
        return self._delete_bone_file("upload", upload_id, path, {f"upload:{upload_id}"},
                                      force)

    def delete_snapshot(self, name: str, force: bool = False) -> dict:
        path = self.snapshot_file(name)
        stem = path.name[: -len(SNAPSHOT_SUFFIX)]
        return self._delete_bone_file("snapshot", stem, path,
                                      {f"snapshot:{stem}", f"snapshot:{path.name}"}, force)

    def _not_being_written(self, name: str) -> Path:
        path = self.recording_dir(name)
        writer = self._writer(path)
        if writer is not None:
            raise Conflict(f"recording {path.name!r} is being written by session {writer}: "
                           f"stop it first (DELETE /v1/sessions/{writer}/recording)")
        return path

    def delete_recording(self, name: str) -> dict:
        """Remove a recording; Conflict while a session writes it."""
        path = self._not_being_written(name)
        size = tree_bytes(path)[0]
        shutil.rmtree(path)
        return _deleted("recording", path.name, size, [], None)

    def export_file(self, name: str) -> Path:
        """The file of export ``name`` in exports/."""
        name = plain_name(name, "export")
        if not EXPORT_NAME.match(name):
            raise BadName(f"export name {name!r}: letters, digits, '_', '-', '.' only, as "
                          "GET /v1/exports lists them")
        path = self.exports_dir / name
        if not path.is_file():
            raise NotFound(f"no export {name!r}")
        return _inside(self.exports_dir, path, "export", name)

    def list_exports(self) -> list[dict]:
        """Exports being served, or left by a download that never finished: ``name``,
        ``bytes``, ``created`` (Unix s)."""
        out = []
        for path in sorted(self.exports_dir.iterdir()):
            if path.name.startswith(".") or path.is_symlink() or not path.is_file():
                continue  # a write under way is not an export yet
            st = path.stat()
            out.append({"name": path.name, "bytes": st.st_size, "created": st.st_mtime})
        return out

    def delete_export(self, name: str) -> dict:
        """Remove an export (one being downloaded goes on being sent: its file is open)."""
        path = self.export_file(name)
        size = path.stat().st_size
        path.unlink(missing_ok=True)
        return _deleted("export", path.name, size, [], None)

    def recording_archive(self, name: str) -> Archive:
        """Recording ``name`` as a tar archive; Conflict while a session writes it (its files
        are still growing, so an archive of them would not be one recording)."""
        return tar_archive(self._not_being_written(name))
