"""Resuming the journaled sessions when ``serve`` starts, whatever state their files are in.

Each session comes back with its id and key, its bone loaded from its source and every intact
record of its carve log replayed onto it (``journal_carve``), its removal and forbidden
contacts with it (``bone.tally``). What could not come back is measured against the journal's
last pass (``journal_state``) and said — in the console and log, in ``/v1/health``, in the
session's view and in its report (``Recovery``). Damaged files are kept beside the new ones
(``carve.log.damaged-<time>``); a session that cannot be resumed at all (a ``session.json``
that fails its checks, a source that is gone) has its folder kept as ``<id>.failed-<time>``
and named in ``/v1/health``. Nothing here raises: ``serve`` always starts.
"""

from __future__ import annotations

import logging
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..bone import Bone
from ..bone.tally import N_LABELS, CarveTally, removal_of
from .config import is_loopback
from .errors import ApiError
from .journal_carve import (
    LogContent,
    apply_log,
    check_fits,
    empty_log,
    keep_aside,
    read_carving,
)
from .journal_record import RecordError, read_record
from .journal_state import JournalState, read_state
from .models import Features, Parameters
from .plane import ControlPlane
from .sessions import ManagedSession
from .sources import SourceError, file_source
from .workers import next_stream_after

log = logging.getLogger("burrforce.journal")

#: Journals not written for this long are discarded at start.
MAX_AGE_DAYS = 30
SESSION_FILE = "session.json"
CARVE_FILE = "carve.log"
STATE_FILE = "state.bin"


@dataclass
class Recovery:
    """What resuming one session could not bring back, measured against the journal's last
    pass (``journal_state``).

    Attributes:
        session: its id.
        bricks: carved bricks the log held that the resumed bone lacks, plus those changed
            after the log's last write (their latest carving is lost).
        removed_mm3: bone the trainee had removed that the resumed bone has again, mm³
            (exact: the tally's removal against the replayed carving's).
        contacts: forbidden contacts whose time, place and label were lost (still counted).
        versions: bone versions lost (the version at the last pass − the resumed one).
        causes: what happened to the files (damaged bytes, a log behind, a missing state).
        kept: the damaged files, kept under these names (relative to the data directory).
        measured: False when there was no journal state to measure against (a journal from
            before it existed, or a damaged state): the loss is then unknown.
    """

    session: int
    bricks: int = 0
    removed_mm3: float = 0.0
    contacts: int = 0
    versions: int = 0
    causes: list[str] = field(default_factory=list)
    kept: list[str] = field(default_factory=list)
    measured: bool = True

    @property
    def lost_anything(self) -> bool:
        return bool(self.bricks or self.removed_mm3 > 0 or self.contacts or self.versions
                    or self.causes)

    @property
    def summary(self) -> str:
        if not self.measured:
            what = ["what was lost is unknown (no journal state to measure it against)"]
        else:
            what = [f"lost {self.removed_mm3:.3f} mm³ of carving in {self.bricks} brick(s)"]
            if self.versions:
                what.append(f"the last {self.versions} bone version(s)")
            if self.contacts:
                what.append(f"{self.contacts} forbidden contact(s)")
        return ", ".join(what) + "".join(f"; {c}" for c in self.causes)

    def as_dict(self) -> dict:
        return {**asdict(self), "summary": self.summary}


@dataclass
class Quarantined:
    """A session folder that could not be resumed, kept for a human (``/v1/health``);
    ``folder`` is relative to the data directory."""

    session: str
    folder: str
    reason: str


@dataclass
class Resumed:
    """What ``resume`` did: the sessions back, what they lost, the folders kept aside."""

    ids: list[int] = field(default_factory=list)
    recoveries: list[Recovery] = field(default_factory=list)
    quarantined: list[Quarantined] = field(default_factory=list)


#: What the journal's writer is handed for a resumed session (``Journal.adopt``).
Adopt = Callable[[ManagedSession, LogContent, int, int | None], None]


def resume(plane: ControlPlane, root: Path, adopt: Adopt,
           say: Callable[[str], None]) -> Resumed:
    """Create every journaled session under ``root`` again, carving and all. Never raises."""
    out = Resumed()
    if not root.is_dir():
        return out
    folders = [p for p in root.iterdir() if p.is_dir() and p.name.isdigit()]
    for folder in sorted(folders, key=lambda p: int(p.name)):
        try:
            _resume_folder(plane, folder, adopt, say, out)
        except Exception as exc:  # anything: the next session, and serve, go on
            log.exception("journal: resuming %s failed", folder)
            _quarantine(plane, folder, f"{type(exc).__name__}: {exc}", say, out)
    return out


def _resume_folder(plane: ControlPlane, folder: Path, adopt: Adopt,
                   say: Callable[[str], None], out: Resumed) -> None:
    path = folder / SESSION_FILE
    if not path.exists():
        if any(p.is_file() and p.stat().st_size for p in folder.iterdir()):
            _quarantine(plane, folder, f"its {SESSION_FILE} is missing", say, out)
        else:
            shutil.rmtree(folder, ignore_errors=True)  # a session that never got ready
        return
    age_days = (time.time() - path.stat().st_mtime) / 86400
    if age_days > MAX_AGE_DAYS:
        say(f"journal: session {folder.name} unused for {age_days:.0f} days: discarded")
        shutil.rmtree(folder, ignore_errors=True)
        return
    try:
        record = read_record(path)
        if str(record["id"]) != folder.name:
            raise RecordError(f"{SESSION_FILE} is for session {record['id']}")
        if record.get("key_hex") is None and not is_loopback(plane.config.host):
            raise RecordError(f"it has no key, and this server listens on "
                              f"{plane.config.host}, which other machines reach (keyless "
                              "sessions are for loopback)")
    except RecordError as exc:
        _quarantine(plane, folder, str(exc), say, out)
        return
    content = read_carving(folder / CARVE_FILE)
    state = read_state(folder / STATE_FILE)
    log_id = record.get("carve_log")
    stale = None
    if log_id is not None and content.scan.log_id not in (None, log_id):
        # The log of the bone the session had before (a reset or a load whose first pass
        # never came): not this bone's carving.
        stale = keep_aside(folder / CARVE_FILE, "stale")
        content = empty_log()
    if state is not None and log_id is not None and state.log_id != log_id:
        state = None
    replayed: dict = {}
    try:
        session = _create(plane, record, content, replayed)
    except (ApiError, SourceError, ValueError, KeyError, TypeError, OSError) as exc:
        _quarantine(plane, folder, exc.detail if isinstance(exc, ApiError) else str(exc),
                    say, out)
        return
    if session.state != "ready":
        # Aside first: deleting the session removes a journal folder still named <id>.
        _quarantine(plane, folder, session.error or "the bone did not load", say, out)
        try:
            plane.delete_session(session.id, keep_journal=True)
        except ApiError:
            pass
        return
    recovery = measure(session.id, content, state, replayed,
                       has_state=(folder / STATE_FILE).exists())
    if recovery.lost_anything:
        for name in (CARVE_FILE, STATE_FILE):
            aside = keep_aside(folder / name, "damaged")
            if aside is not None:
                recovery.kept.append(in_data_dir(plane.data_dir, aside))
        session.journal.recovery = recovery.as_dict()
        out.recoveries.append(recovery)
        text = (f"journal: session {session.id} resumed with its key, up to its journal's "
                f"last good records: {recovery.summary}")
        say(text)
        log.warning(text)
    else:
        say(f"journal: resumed session {session.id} ({len(content.index)} carved brick(s) "
            f"replayed)")
    if stale is not None:
        say(f"journal: session {session.id}: the carve log of its earlier bone is kept as "
            f"{stale}")
    adopt(session, content, replayed.get("version", 0), log_id)
    out.ids.append(session.id)


def _create(plane: ControlPlane, record: dict, content: LogContent,
            replayed: dict) -> ManagedSession:
    """The session ``record`` describes, once its load ended (ready, or failed with its
    ``error``), its carving replayed (``replayed`` gets the bone version, the removal and the
    voxel volume). Raises what a session that cannot even be created raises."""
    sid = int(record["id"])
    src = record["source"]
    if src["source"].startswith("file:"):
        source = file_source(src["source"], Path(src["path"]), src["kind"])
    else:
        source = plane.resolve(src["source"], src["kind"], src["voxel_mm"],
                               tuple(src["spacing_mm"]) if src["spacing_mm"] else None)

    def prepare(session: ManagedSession) -> None:
        session.primary_label = record["primary_label"]
        session.overrides = {(None if k == "primary" else int(k)): v
                             for k, v in record["overrides"].items()}
        session.calibrations = {int(k): v for k, v in record["calibrations"].items()}
        session.created_s = float(record["created"])
        if record.get("next_stream"):
            session.next_stream = next_stream_after(int(record["next_stream"]))
        session.pending_carve = replay

    def replay(bone: Bone) -> CarveTally:
        check_fits(bone.grid, content.index)
        units = removal_of(bone.grid, content.index, content.swept)
        apply_log(bone.grid, content.index, content.version, content.swept)
        tally = CarveTally.private()
        first, rows = content.contact_rows
        tally.load(units, first + len(rows), first, rows)
        replayed.update(version=bone.grid.version, units=units,
                        voxel_mm3=bone.grid.voxel_volume_mm3)
        return tally

    session, job = plane.create_session(
        sid, source, Parameters(**record["parameters"]), Features(**record["features"]),
        authenticated=record["key_hex"] is not None, key_hex=record["key_hex"],
        prepare=prepare, worker=record.get("worker"))
    plane.wait(job)
    return session


def measure(session_id: int, content: LogContent, state: JournalState | None,
            replayed: dict, has_state: bool) -> Recovery:
    """What the resumed session lacks of what the journal's last pass (``state``) knew."""
    found = content.scan
    out = Recovery(session_id)
    if found.damaged:
        out.causes.append(f"{CARVE_FILE}: {found.damaged_bytes} damaged byte(s) in "
                          f"{len(found.damaged)} place(s) skipped")
    if found.header_damaged:
        out.causes.append(f"{CARVE_FILE}: its header is damaged")
    if state is None:
        out.measured = False
        if has_state:
            out.causes.append(f"{STATE_FILE} is damaged")
        return out
    expected = np.zeros(N_LABELS)
    for label, v in state.removed.items():
        expected[int(label)] = v
    units = replayed.get("units", np.zeros(N_LABELS))
    lost_units = float((expected - units).sum())
    out.removed_mm3 = max(0.0, lost_units * replayed.get("voxel_mm3", 0.0) / 255.0 ** 2)
    out.versions = max(0, state.bone_version - replayed.get("version", 0))
    out.bricks = max(0, int(state.log.get("bricks", 0)) - len(content.index)) \
        + state.unlogged_bricks
    out.contacts = max(0, state.contacts - content.contacts_begun)
    if not (out.removed_mm3 > 0 or out.bricks or out.versions or out.contacts):
        return out  # the log holds all the last pass knew (or more: a crash before its state)
    if state.behind_since is not None:
        since = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(state.behind_since))
        out.causes.append(f"the journal could not be written from {since} "
                          f"({state.error or 'an error'}): what was cut since is lost")
    had = int(state.log.get("bytes", 0))
    if found.size < had and not found.damaged:
        out.causes.append(f"{CARVE_FILE} holds {found.size} of the {had} bytes it had")
    return out


def in_data_dir(data_dir: Path, path: Path) -> str:
    """``path`` relative to the data directory (what /v1/health, which needs no token,
    shows: where, not the machine's layout)."""
    try:
        return str(path.relative_to(data_dir))
    except ValueError:
        return path.name


def _quarantine(plane: ControlPlane, folder: Path, reason: str,
                say: Callable[[str], None], out: Resumed) -> None:
    """Keep ``folder`` aside as ``<id>.failed-<time>`` with a note of why."""
    aside = folder.with_name(f"{folder.name}.failed-{time.strftime('%Y%m%d-%H%M%S')}")
    n = 1
    while aside.exists():
        n += 1
        aside = folder.with_name(f"{folder.name}.failed-{time.strftime('%Y%m%d-%H%M%S')}-{n}")
    try:
        folder.rename(aside)
    except OSError as exc:
        log.error("journal: %s could not be moved aside (%s): left where it is", folder, exc)
        aside = folder
    try:
        (aside / "WHY.txt").write_text(reason + "\n")
    except OSError:
        pass
    out.quarantined.append(Quarantined(folder.name, in_data_dir(plane.data_dir, aside), reason))
    text = (f"journal: session {folder.name} could not be resumed ({reason}); its journal "
            f"is kept in {aside}")
    say(text)
    log.error(text)
