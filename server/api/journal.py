"""The session journal: sessions and their carving outlive a crash, a reboot or a restart.

Every ``INTERVAL_S`` a thread of the control plane writes, for each session, what it takes to
build it again (``session.json``: id, key, bone source, parameters, features, material
changes, calibrations, the next stream number) and appends the bricks its burr changed since
the last pass to its carve log (``journal_carve``). Both writes are cheap (a few kB a second
while cutting) and never touch the hot loop: the bricks are read from the bone the control
plane already maps.

``burrforce serve`` then resumes the journaled sessions (``resume``): the same ids and keys,
the bone loaded from its source again with the carve log replayed onto it, so at most the
last interval of cutting is lost. Layout::

    DATA_DIR/journal/sessions/<id>/session.json   (mode 0600: it holds the key)
    DATA_DIR/journal/sessions/<id>/carve.log

A session's journal goes when the session is deleted over REST, when ``serve --fresh``
starts, or when it has not been written for ``MAX_AGE_DAYS``.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from .config import is_loopback
from .daemon import start_daemon, stop_daemon
from .errors import ApiError
from .housekeeping import journal_dir
from .journal_carve import CarveLog, apply_log, read_log, write_atomic
from .models import Features, Parameters
from .plane import ControlPlane
from .sessions import ManagedSession
from .sources import SourceError, file_source
from .views import parameters_view
from .workers import later_stream, next_stream_after

log = logging.getLogger("burrforce.journal")

FORMAT = "burrforce-journal"
FORMAT_VERSION = 1
#: Seconds between two passes: the most cutting a crash can lose.
INTERVAL_S = 1.0
#: Journals not written for this long are discarded at start.
MAX_AGE_DAYS = 30
SESSION_FILE = "session.json"
CARVE_FILE = "carve.log"


def session_record(session: ManagedSession, stream: int | None) -> dict:
    """What it takes to build ``session`` again (JSON-ready)."""
    params = parameters_view(session)
    params.pop("burr_calibrated")  # follows from the burr
    params.pop("burr_profile_mm")  # likewise
    for name in ("us_n_mm2", "k", "primary_material_name"):  # in the material changes
        params.pop(name)
    source = session.source
    return {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "id": session.id, "key_hex": session.key_hex,
        "source": {"source": source.source, "kind": source.kind,
                   "voxel_mm": source.voxel_mm,
                   "spacing_mm": list(source.spacing_mm) if source.spacing_mm else None,
                   "path": str(source.path) if source.path is not None else None},
        "parameters": params,
        "features": session.features.model_dump(),
        "primary_label": session.primary_label,
        # JSON keys are strings: None (the primary material, before a bone) is "primary".
        "overrides": {("primary" if k is None else str(k)): v
                      for k, v in session.overrides.items()},
        "calibrations": {str(k): v for k, v in session.calibrations.items()},
        "created": session.created_s,
        "next_stream": stream,
        # Its worker's UDP port is the one its engine streams to: resumed on the same one.
        "worker": session.worker,
        "bone_generation": (session.bone_info or {}).get("generation"),
    }


class Journal:
    """Writes the journal of ``plane``'s sessions from a thread (``start``/``stop``)."""

    def __init__(self, plane: ControlPlane, stream_of: Callable[[int], int | None],
                 interval_s: float = INTERVAL_S) -> None:
        self.plane = plane
        self.root = journal_dir(plane.data_dir)
        self.stream_of = stream_of
        self.interval_s = interval_s
        self._written: dict[int, str] = {}
        self._logs: dict[int, tuple[object, CarveLog]] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.passes = 0
        self.errors = 0
        self.last_error: str | None = None

    def start(self) -> None:
        self._thread = start_daemon(self._run, "burrforce-journal")

    def stop(self) -> None:
        """A last pass, then stop: a clean shutdown keeps every session for the next start."""
        stop_daemon(self._stop, self._thread)
        self._thread = None
        self.write()

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.write()

    def adopt(self, session_id: int, ref: object, since_version: int) -> None:
        """A resumed session's log already holds its carving up to ``since_version``."""
        self._logs[session_id] = (ref, CarveLog(self.root / str(session_id) / CARVE_FILE,
                                                since_version))

    def write(self) -> None:
        """One pass: every session's record if it changed, the bricks carved since the last
        pass, and the journals of deleted sessions removed."""
        try:
            self._write()
            self.passes += 1
        except Exception as exc:  # a full disk must not stop the journal for good
            self.errors += 1
            if str(exc) != self.last_error:
                log.error("the session journal could not be written: %s", exc)
            self.last_error = str(exc)

    def _write(self) -> None:
        for sid, session in list(self.plane.sessions.items()):
            # Under the session's lock, which a delete holds while it removes the session
            # and its journal: a pass never writes a deleted session back. A session busy
            # with a bone swap is taken at the next pass.
            if not session.lock.acquire(timeout=0.1):
                continue
            try:
                if self.plane.sessions.get(sid) is session:
                    self._write_session(sid, session)
            finally:
                session.lock.release()
        live = self.plane.sessions
        for sid in list(self._written) + [int(p.name) for p in self.folders()]:
            if sid not in live:
                shutil.rmtree(self.root / str(sid), ignore_errors=True)
                self._written.pop(sid, None)
                self._logs.pop(sid, None)

    def _write_session(self, sid: int, session: ManagedSession) -> None:
        if session.state != "ready":
            return  # a first load in progress or failed: nothing to resume yet
        folder = self.root / str(sid)
        # The later of what the loop reported and what it was started with.
        stream = later_stream(self.stream_of(sid), session.next_stream)
        record = json.dumps(session_record(session, stream), indent=1, sort_keys=True)
        path = folder / SESSION_FILE
        if self._written.get(sid) != record:
            write_atomic(path, record.encode())
            self._written[sid] = record
        else:
            try:  # in use: MAX_AGE_DAYS counts from the last pass, not the last change
                os.utime(path)
            except FileNotFoundError:
                write_atomic(path, record.encode())
        reader, ref = session.reader, session.ref
        if reader is None:
            return
        known = self._logs.get(sid)
        if known is None or known[0] is not ref:  # a new bone: its carving starts over
            carve = CarveLog(folder / CARVE_FILE)
            carve.reset(0)
            self._logs[sid] = (ref, carve)
        else:
            carve = known[1]
        carve.append(reader.swept, reader.brick_version)

    def folders(self) -> list[Path]:
        """The journal's session folders (named by session id)."""
        if not self.root.is_dir():
            return []
        return [p for p in self.root.iterdir() if p.is_dir() and p.name.isdigit()]


def discard(data_dir: Path) -> int:
    """``serve --fresh``: remove every journaled session; returns how many there were."""
    root = journal_dir(data_dir)
    n = len([p for p in root.iterdir() if p.is_dir()]) if root.is_dir() else 0
    shutil.rmtree(root, ignore_errors=True)
    return n


def discard_session(data_dir: Path, session_id: int) -> bool:
    """Forget one journaled session; returns whether there was one."""
    folder = journal_dir(data_dir) / str(session_id)
    existed = folder.is_dir()
    shutil.rmtree(folder, ignore_errors=True)
    return existed


def resume(plane: ControlPlane, journal: Journal, say: Callable[[str], None]) -> list[int]:
    """Create every journaled session again, carving and all; returns the ids resumed.

    Sessions whose journal cannot be used (a source that is gone, a damaged file) are
    reported and their journal is kept aside as ``<id>.failed-<time>`` for a human to
    look at, never silently dropped."""
    root = journal.root
    if not root.is_dir():
        return []
    resumed = []
    for folder in sorted(journal.folders(), key=lambda p: int(p.name)):
        path = folder / SESSION_FILE
        try:
            age_days = (time.time() - path.stat().st_mtime) / 86400
        except FileNotFoundError:
            shutil.rmtree(folder, ignore_errors=True)  # a session that never got ready
            continue
        if age_days > MAX_AGE_DAYS:
            say(f"journal: session {folder.name} unused for {age_days:.0f} days: discarded")
            shutil.rmtree(folder, ignore_errors=True)
            continue
        try:
            sid, carved = _resume_one(plane, journal, folder)
        except (ApiError, SourceError, ValueError, KeyError, TypeError, OSError) as exc:
            reason = exc.detail if isinstance(exc, ApiError) else str(exc)
            aside = folder.with_name(f"{folder.name}.failed-{time.strftime('%Y%m%d-%H%M%S')}")
            folder.rename(aside)
            say(f"journal: session {folder.name} could not be resumed ({reason}); its "
                f"journal is kept in {aside}")
            continue
        resumed.append(sid)
        say(f"journal: resumed session {sid} ({carved} carved brick(s) replayed)")
    return resumed


def _resume_one(plane: ControlPlane, journal: Journal, folder: Path) -> tuple[int, int]:
    record = json.loads((folder / SESSION_FILE).read_text())
    if record.get("format") != FORMAT or record.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"not a {FORMAT} v{FORMAT_VERSION} record")
    if record["key_hex"] is None and not is_loopback(plane.config.host):
        raise ValueError(f"it has no key, and this server listens on {plane.config.host}, "
                         "which other machines reach (keyless sessions are for loopback)")
    sid = int(record["id"])
    src = record["source"]
    if src["source"].startswith("file:"):
        source = file_source(src["source"], Path(src["path"]), src["kind"])
    else:
        source = plane.resolve(src["source"], src["kind"], src["voxel_mm"],
                               tuple(src["spacing_mm"]) if src["spacing_mm"] else None)
    index, version, swept = read_log(folder / CARVE_FILE)
    carved = {"since": 0}

    def prepare(session: ManagedSession) -> None:
        session.primary_label = record["primary_label"]
        session.overrides = {(None if k == "primary" else int(k)): v
                             for k, v in record["overrides"].items()}
        session.calibrations = {int(k): v for k, v in record["calibrations"].items()}
        session.created_s = float(record["created"])
        if record.get("next_stream"):
            session.next_stream = next_stream_after(int(record["next_stream"]))

        def replay(bone) -> None:
            apply_log(bone.grid, index, version, swept)
            carved["since"] = int(version.max()) if len(version) else 0
        session.pending_carve = replay

    session, job = plane.create_session(
        sid, source, Parameters(**record["parameters"]), Features(**record["features"]),
        authenticated=record["key_hex"] is not None, key_hex=record["key_hex"],
        prepare=prepare, worker=record.get("worker"))
    plane.wait(job)
    if session.state != "ready":
        plane.delete_session(sid)
        raise ValueError(session.error or "the bone did not load")
    journal.adopt(sid, session.ref, carved["since"])
    return sid, len(index)
