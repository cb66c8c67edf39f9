"""The session journal: sessions and their carving outlive a crash, a reboot or a restart.

Every ``INTERVAL_S`` a thread of the control plane writes, for each session, what it takes to
build it again (``session.json``: id, key, bone source, parameters, features, material
changes, calibrations, the next stream number, the id of its carve log; ``journal_record``),
appends the bricks its burr changed and the forbidden contacts it began since the last pass to
its carve log (``journal_carve``), and overwrites its state (``state.bin``: the bone's removal,
contacts and version and what the log holds; ``journal_state``) — the yardstick a restart
measures any loss against. The bricks and the tally are read from the bone the control plane
already maps, at one moment between two ticks (``SharedBone.carving_since``); nothing of it runs
in the hot loop. Layout::

    DATA_DIR/journal/sessions/<id>/session.json   (mode 0600: it holds the key)
    DATA_DIR/journal/sessions/<id>/carve.log
    DATA_DIR/journal/sessions/<id>/state.bin

``burrforce serve`` then resumes the journaled sessions (``journal_resume``). A pass that
cannot write (a full disk) marks the session's journal ``degraded`` — in its view,
``/v1/health`` and ``/metrics`` — and the next pass tries again; the state file, written in
place, records how far behind the log is, so a restart in that window says what it lost.

A session's journal goes when the session is deleted over REST, when ``serve --fresh``
starts, or when it has not been written for ``MAX_AGE_DAYS``.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import threading
import time
from collections.abc import Callable
from pathlib import Path

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from .daemon import start_daemon, stop_daemon
from .housekeeping import journal_dir
from .journal_carve import CarveLog, LogContent
from .journal_format import write_atomic
from .journal_record import sealed, session_record
from .journal_resume import (
    CARVE_FILE,
    MAX_AGE_DAYS,
    SESSION_FILE,
    STATE_FILE,
    Resumed,
    in_data_dir,
)
from .journal_resume import resume as resume_sessions
from .journal_state import JournalState, StateFile
from .plane import ControlPlane
from .sessions import ManagedSession
from .workers import later_stream

log = logging.getLogger("burrforce.journal")

__all__ = ["MAX_AGE_DAYS", "Journal", "discard", "discard_session", "resume"]

#: Seconds between two passes: the most cutting a crash can lose.
INTERVAL_S = 1.0


class BoneJournal:
    """One session's journal files for its current bone: the carve log and the state file,
    written afresh (``started``) once ``session.json`` names the log."""

    def __init__(self, folder: Path, ref: object, log_id: int, since_version: int = 0,
                 content: LogContent | None = None) -> None:
        self.ref = ref
        self.log_id = log_id
        self.carve = CarveLog(folder / CARVE_FILE, since_version, log_id)
        self.state = StateFile(folder / STATE_FILE)
        #: What the log starts with (a resumed session's replayed carving).
        self.content = content
        self.started = False
        self.state_made = False
        #: When appending to the log began to fail (None while it succeeds).
        self.behind_since: float | None = None


def new_log_id() -> int:
    return secrets.randbits(62) + 1


class Journal:
    """Writes the journal of ``plane``'s sessions from a thread (``start``/``stop``)."""

    def __init__(self, plane: ControlPlane, stream_of: Callable[[int], int | None],
                 interval_s: float = INTERVAL_S) -> None:
        self.plane = plane
        self.root = journal_dir(plane.data_dir)
        self.stream_of = stream_of
        self.interval_s = interval_s
        self._written: dict[int, str] = {}
        self._bones: dict[int, BoneJournal] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.passes = 0
        #: Session passes that failed to write something (a full disk).
        self.errors = 0
        self.last_error: str | None = None
        #: What the resume at start did (``journal_resume.Resumed``).
        self.resumed = Resumed()
        self._reasons: dict[str, str] = {}

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

    def adopt(self, session: ManagedSession, content: LogContent, since_version: int,
              log_id: int | None) -> None:
        """A resumed session: its log starts with the carving just replayed (``content``,
        stamped up to ``since_version``), written now rather than at the next pass (the
        damaged files it replaces are kept aside already)."""
        folder = self.root / str(session.id)
        self._bones[session.id] = BoneJournal(folder, session.ref, log_id or new_log_id(),
                                              since_version, content)
        with session.lock:
            self._write_one(session.id, session)

    def write(self) -> None:
        """One pass: every session's record if it changed, the carving since the last pass,
        its state; the journals of deleted sessions removed."""
        for sid, session in list(self.plane.sessions.items()):
            # Under the session's lock, which a delete holds while it removes the session
            # and its journal: a pass never writes a deleted session back. A session busy
            # with a bone swap is taken at the next pass.
            if not session.lock.acquire(timeout=0.1):
                continue
            try:
                if self.plane.sessions.get(sid) is session:
                    self._write_one(sid, session)
            finally:
                session.lock.release()
        live = self.plane.sessions
        for sid in list(self._written) + [int(p.name) for p in self.folders()]:
            if sid not in live:
                shutil.rmtree(self.root / str(sid), ignore_errors=True)
                self._written.pop(sid, None)
                self._bones.pop(sid, None)
        self.passes += 1

    def _write_one(self, sid: int, session: ManagedSession) -> None:
        """``_write_session``, its outcome in the session's journal status; never raises (a
        full disk must not stop the journal, nor one session's trouble the others')."""
        now = time.time()
        try:
            problems = self._write_session(sid, session, now)
        except Exception as exc:
            log.exception("journal: session %s", sid)
            problems = [f"{type(exc).__name__}: {exc}"]
        if session.state != "ready":
            return
        if not problems:
            if session.journal.state == "degraded":
                log.warning("journal: session %s is written again", sid)
            session.journal.written(now)
            return
        self.errors += 1
        error = "; ".join(problems)
        if error != session.journal.error:
            log.error("the journal of session %s could not be written: %s", sid, error)
        self.last_error = error
        session.journal.failed(error, now)

    def _write_session(self, sid: int, session: ManagedSession, now: float) -> list[str]:
        """One session's pass; returns what could not be written."""
        reader = session.reader
        if session.state != "ready" or reader is None:
            return []  # a first load in progress or failed: nothing to resume yet
        folder = self.root / str(sid)
        bone = self._bones.get(sid)
        if bone is None or bone.ref is not session.ref:  # a new bone: its carving starts over
            bone = BoneJournal(folder, session.ref, new_log_id())
            self._bones[sid] = bone
        elif bone.started and not (bone.carve.path.exists() and bone.state.path.exists()):
            # Removed behind the journal's back: written again, whole (every brick stamped).
            bone = BoneJournal(folder, session.ref, bone.log_id)
            self._bones[sid] = bone
        problems = []
        # The later of what the loop reported and what it was started with.
        stream = later_stream(self.stream_of(sid), session.next_stream)
        text = sealed({**session_record(session, stream), "carve_log": bone.log_id})
        path = folder / SESSION_FILE
        try:
            try:  # in use: MAX_AGE_DAYS counts from the last pass, not the last change
                if self._written.get(sid) == text:
                    os.utime(path)
            except FileNotFoundError:
                self._written.pop(sid)
            if self._written.get(sid) != text:
                write_atomic(path, text.encode())
                self._written[sid] = text
        except OSError as exc:
            self._written.pop(sid, None)
            problems.append(f"{SESSION_FILE}: {_why(exc)}")
        if not bone.started and self._written.get(sid) == text:
            # Only once session.json names this log: a log it does not name is not replayed.
            try:
                bone.carve.start(bone.content, bone.carve.since_version)
                bone.started, bone.content = True, None
            except OSError as exc:
                problems.append(f"{CARVE_FILE}: {_why(exc)}")
        take = reader.carving_since(bone.carve.since_version)
        first, rows = reader.tally.rows_since(bone.carve.contacts)
        unlogged = len(take.index)
        if bone.started:
            top = int(take.version.max()) if len(take.version) else bone.carve.since_version
            try:
                bone.carve.append_carving(take.index, take.version, take.blocks, top,
                                          (first, rows))
                unlogged, bone.behind_since = 0, None
            except OSError as exc:
                problems.append(f"{CARVE_FILE}: {_why(exc)}")
        if unlogged and bone.behind_since is None:
            bone.behind_since = now
        carve = bone.carve
        state = JournalState(
            bone.log_id, now, take.bone_version,
            {str(k): float(v) for k, v in enumerate(take.removed) if v},
            first + len(rows),
            {"bytes": carve.size, "records": carve.records, "bricks": carve.bricks,
             "version": carve.version, "contacts": carve.contacts},
            unlogged, bone.behind_since, "; ".join(problems) or None)
        if bone.started:
            try:
                if bone.state_made:
                    bone.state.write(state)
                else:
                    bone.state.create(state)
                    bone.state_made = True
            except OSError as exc:
                problems.append(f"{STATE_FILE}: {_why(exc)}")
        return problems

    def folders(self) -> list[Path]:
        """The journal's session folders (named by session id)."""
        if not self.root.is_dir():
            return []
        return [p for p in self.root.iterdir() if p.is_dir() and p.name.isdigit()]

    def kept_aside(self) -> list[dict]:
        """Session folders a resume could not use, kept for a human (``<id>.failed-…``,
        relative to the data directory), and why."""
        if not self.root.is_dir():
            return []
        out = []
        # This start's reasons first: a WHY.txt may not have fitted a full disk.
        known = {Path(q.folder).name: q.reason for q in self.resumed.quarantined}
        for p in sorted(self.root.iterdir()):
            if not (p.is_dir() and ".failed-" in p.name):
                continue
            if p.name in known:
                self._reasons[p.name] = known[p.name]
            if p.name not in self._reasons:
                try:
                    self._reasons[p.name] = (p / "WHY.txt").read_text().strip()
                except OSError:
                    self._reasons[p.name] = "unknown (no WHY.txt)"
            out.append({"folder": in_data_dir(self.plane.data_dir, p),
                        "session": p.name.split(".", 1)[0],
                        "reason": self._reasons[p.name]})
        return out

    # -- health and metrics -------------------------------------------------------------------
    def public(self) -> dict:
        """``/v1/health``'s ``journal``: ok or degraded (which sessions, why, since when),
        what this start's resume lost, the session folders kept aside."""
        sessions = list(self.plane.sessions.values())
        degraded = sorted(s.id for s in sessions if s.journal.state == "degraded")
        since = [s.journal.failing_since_s for s in sessions if s.journal.failing_since_s]
        return {
            "state": "degraded" if degraded else "ok",
            "degraded_sessions": degraded,
            "error": next((s.journal.error for s in sessions if s.journal.error), None),
            "failing_since": min(since) if since else None,
            "passes": self.passes,
            "recovered": [r.as_dict() for r in self.resumed.recoveries],
            "quarantined": self.kept_aside(),
        }

    def collect(self):  # the prometheus_client collector protocol
        sessions = sorted(self.plane.sessions.values(), key=lambda s: s.id)
        up = GaugeMetricFamily("burrforce_journal_up", "1 while every session's journal is "
                               "written, 0 while one cannot be (degraded)")
        up.add_metric([], 0.0 if any(s.journal.state == "degraded" for s in sessions)
                      else 1.0)
        failures = CounterMetricFamily("burrforce_journal_write_failures", "Session journal "
                                       "passes that could not write everything")
        failures.add_metric([], self.errors)
        degraded = GaugeMetricFamily("burrforce_journal_degraded", "1 while the session's "
                                     "journal cannot be written", labels=["session"])
        lost = GaugeMetricFamily("burrforce_journal_lost_mm3", "Carving the session's resume "
                                 "could not bring back from its journal, mm³",
                                 labels=["session"])
        for s in sessions:
            degraded.add_metric([str(s.id)], 1.0 if s.journal.state == "degraded" else 0.0)
            if s.journal.recovery is not None:
                lost.add_metric([str(s.id)], s.journal.recovery["removed_mm3"])
        kept = GaugeMetricFamily("burrforce_journal_quarantined", "Journaled sessions that "
                                 "could not be resumed, kept aside")
        kept.add_metric([], len(self.kept_aside()))
        yield from (up, failures, degraded, lost, kept)


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


def resume(plane: ControlPlane, journal: Journal, say: Callable[[str], None]) -> list[int]:
    """Create every journaled session again, carving and all (``journal_resume``); returns
    the ids resumed. Never raises."""
    journal.resumed = resume_sessions(plane, journal.root, journal.adopt, say)
    return journal.resumed.ids


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

