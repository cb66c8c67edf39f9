"""The data directory as the user sees it: what is stored (uploads, snapshots, recordings and
the exports being served), how much of the budget it takes, writing into it within the budget,
and deleting from it safely. :class:`Storage` is the only code that lists, sizes or deletes
these files.

The budget (``ServeConfig.data_budget_bytes``, 0: none) counts every file under uploads/,
snapshots/, recordings/ and exports/; the journal (data_dir/journal) is reported but not
counted, since the server needs it whatever the user keeps. A running recording holds room up
to its ``max_bytes`` (reserved): it was capped by the room left when it started, so it stops
cleanly at the budget instead of filling the disk, and other writes cannot take that room
from it.

Names from URLs are resolved here and only here: a name is one plain path component of the
kind's form (an upload id, a snapshot or recording name), never ``..``, a slash, an absolute
path or a NUL, so nothing outside the kind's folder can be listed, read or deleted.

Raises the domain errors of ``errors`` (BadName, NotFound, Conflict, NoRoom, TooLarge).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ..bone import Bone
from ..bone.loaders import save_bone
from .archive import Archive, tar_archive
from .errors import ApiError, BadName, Conflict, NoRoom, NotFound
from .jobs import JobTable
from .sessions import SessionTable
from .sources import SNAPSHOT_SUFFIX, UPLOAD_ID, SourceError, SourceRoots, snapshot_path

#: Folders of the data directory the budget counts, by kind.
COUNTED = ("uploads", "snapshots", "recordings", "exports")
#: Folders reported but not counted.
UNCOUNTED = ("journal",)
RECORDING_SUFFIX = ".burrrec"
RECORDING_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
#: Room a recording needs beyond its chunk files (which ``max_bytes`` bounds): meta, start
#: patch and summary, all small.
RECORDING_MARGIN_BYTES = 64 << 10
#: Where the user looks and what the user deletes, quoted in every over-budget answer.
WHAT_TO_DELETE = ("GET /v1/storage shows what is stored; DELETE /v1/uploads/ID, "
                  "/v1/snapshots/NAME or /v1/recordings/NAME frees it")


# -- usage --------------------------------------------------------------------------------------
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


@dataclass(frozen=True)
class Usage:
    """The data directory's usage at one moment.

    Attributes:
        bytes_by_kind: bytes per folder (``COUNTED`` and ``UNCOUNTED``).
        items_by_kind: uploads, snapshots, recordings and files (exports, journal) per folder.
        reserved_bytes: room held for running recordings (up to their ``max_bytes``).
        budget_bytes: the budget, 0 for none.
    """

    bytes_by_kind: dict[str, int]
    items_by_kind: dict[str, int]
    reserved_bytes: int
    budget_bytes: int

    @property
    def used_bytes(self) -> int:
        return sum(self.bytes_by_kind[k] for k in COUNTED)

    @property
    def free_bytes(self) -> int | None:
        """Room left under the budget (None: no budget; never negative)."""
        if not self.budget_bytes:
            return None
        return max(0, self.budget_bytes - self.used_bytes - self.reserved_bytes)

    def fits(self, incoming_bytes: int) -> bool:
        return not self.budget_bytes or (
            self.used_bytes + self.reserved_bytes + incoming_bytes <= self.budget_bytes)


def _items(kind: str, folder: Path, files: int) -> int:
    if kind == "uploads":
        return len(_upload_files(folder))
    if kind == "snapshots":
        return sum(1 for _ in folder.glob("*" + SNAPSHOT_SUFFIX))
    if kind == "recordings":
        return sum(1 for p in folder.glob("*" + RECORDING_SUFFIX) if p.is_dir())
    return files


def human_bytes(n: int) -> str:
    """``1536`` → ``1.5 KiB``."""
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(value) < 1024 or unit == "TiB":
            return f"{int(value)} B" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


def over_budget(u: Usage, what: str, error: type[ApiError] = NoRoom,
                incoming_bytes: int = 0) -> ApiError:
    """The answer to a write that does not fit: the budget, the usage, what to delete
    (``error``: NoRoom, or TooLarge for an upload)."""
    parts = ", ".join(f"{k} {human_bytes(u.bytes_by_kind[k])}" for k in COUNTED)
    held = (f", {human_bytes(u.reserved_bytes)} held for running recordings"
            if u.reserved_bytes else "")
    size = f" ({human_bytes(incoming_bytes)})" if incoming_bytes else ""
    return error(f"{what}{size} does not fit in the data directory's budget of "
                 f"{human_bytes(u.budget_bytes)} (data_budget_bytes): "
                 f"{human_bytes(u.used_bytes)} is used ({parts}){held}. {WHAT_TO_DELETE}")


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

    # -- usage ------------------------------------------------------------------------------
    def measure(self) -> Usage:
        """What the data directory holds now, and what running recordings may still add."""
        sizes: dict[str, int] = {}
        items: dict[str, int] = {}
        for kind in COUNTED + UNCOUNTED:
            folder = self.data_dir / kind
            sizes[kind], files = tree_bytes(folder)
            items[kind] = _items(kind, folder, files) if folder.is_dir() else 0
        return Usage(sizes, items, self._reserved_bytes(), self.budget_bytes)

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
        """``GET /v1/storage``: usage per kind, the budget, what is left."""
        u = self.measure()
        try:
            disk_free = shutil.disk_usage(self.data_dir).free
        except OSError:
            disk_free = None
        kinds = {kind: {"bytes": u.bytes_by_kind[kind], "items": u.items_by_kind[kind],
                        "counted": kind in COUNTED} for kind in COUNTED + UNCOUNTED}
        for kind in ("uploads", "snapshots", "recordings"):
            kinds[kind]["list"] = f"/v1/{kind}"
        return {"data_dir": str(self.data_dir), "budget_bytes": u.budget_bytes,
                "used_bytes": u.used_bytes, "reserved_bytes": u.reserved_bytes,
                "free_bytes": u.free_bytes, "disk_free_bytes": disk_free, "kinds": kinds}

    def require_room(self, what: str, error: type[ApiError] = NoRoom,
                     incoming_bytes: int = 0) -> Usage:
        """Raise ``error`` unless ``incoming_bytes`` more fit under the budget; with no size
        known (0), unless some room is left at all. Returns the usage measured."""
        u = self.measure()
        full = u.budget_bytes and u.free_bytes == 0
        if not u.fits(incoming_bytes) or (incoming_bytes == 0 and full):
            raise over_budget(u, what, error, incoming_bytes)
        return u

    def check_written(self, path: Path, what: str) -> None:
        """After writing ``path`` (whose size was unknown beforehand): if it took the data
        directory over the budget, remove it and raise NoRoom."""
        u = self.measure()
        if u.fits(0):
            return
        size = tree_bytes(path)[0] if path.is_dir() else path.stat().st_size
        _remove(path)
        raise over_budget(u, what, NoRoom, size)

    def recording_cap(self, max_bytes: int) -> int:
        """``max_bytes`` capped by the room left (measured after the recording's start
        snapshot was written); NoRoom when nothing is left."""
        u = self.measure()
        if not u.budget_bytes:
            return max_bytes
        room = (u.free_bytes or 0) - RECORDING_MARGIN_BYTES
        if room <= 0:
            raise over_budget(u, "a recording", NoRoom)
        return min(max_bytes, room)

    # -- writing ----------------------------------------------------------------------------
    def save_snapshot(self, bone: Bone, name: str | None, session_id: int,
                      generation: int | None) -> dict:
        """Save ``bone`` (session ``session_id``'s, of bone ``generation``) as snapshot
        ``name`` (None: one named after the session, version and time). Conflict if it
        exists; NoRoom over the budget."""
        if name is None:
            name = (f"session-{session_id}-v{bone.grid.version}-"
                    f"{time.strftime('%Y%m%d-%H%M%S')}")
        try:
            path = snapshot_path(self.roots.snapshots, name)
        except SourceError as exc:
            raise exc.as_api_error() from None
        if path.exists():
            raise Conflict(f"snapshot {name!r} exists")
        self.require_room("a snapshot")
        save_bone(bone, path, generation=generation)
        self.check_written(path, "the snapshot")
        return snapshot_entry(path)

    def new_recording_dir(self, name: str) -> Path:
        """An empty folder for recording ``name`` (``.burrrec`` added if missing); Conflict
        if it exists, NoRoom when the budget is full."""
        path = self.recordings_dir / (name if name.endswith(RECORDING_SUFFIX)
                                      else name + RECORDING_SUFFIX)
        if path.exists():
            raise Conflict(f"recording {path.name} exists")
        self.require_room("a recording")
        path.mkdir(parents=True)
        return path

    def export_file(self, suffix: str) -> Path:
        """A new, empty file in exports/ ending in ``suffix`` (the caller writes it, then
        :meth:`check_written`); NoRoom when the budget is full."""
        self.require_room("an export")
        fd, name = tempfile.mkstemp(prefix="export-", suffix=suffix, dir=self.exports_dir)
        os.close(fd)
        return Path(name)

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

    def recording_archive(self, name: str) -> Archive:
        """Recording ``name`` as a tar archive; Conflict while a session writes it (its files
        are still growing, so an archive of them would not be one recording)."""
        return tar_archive(self._not_being_written(name))
