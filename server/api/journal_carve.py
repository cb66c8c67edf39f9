"""The carve log: what a session's burr removed and which forbidden structures it touched, as
records appended to a file (framing and CRCs: ``journal_format``).

A brick record holds the ``swept`` voxels of the bricks that changed since the previous
record, each with the bone version that last changed it. Replayed in order onto the bone its
source loads, the records give back the carved bone (the later record of a brick wins). Only
the bricks that changed are written, so a second of cutting costs a few kB, not the bone. A
contact record holds forbidden contacts begun since the previous one, each with its number
(the first contact of the bone is 0), so a contact read twice counts once.

Payloads (little-endian)::

    bricks (b"BFCR"):   index int32[n, 3] (brick coordinates), version int64[n],
                        swept uint8[n, 8, 8, 8] (bricks on the grid's far edges padded with 0)
    contacts (b"BFCT"): number int64[n], contact float64[n, 5] (time_s, x, y, z mm, label)
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bone.bricks import BRICK
from ..bone.grid import BoneGrid
from ..bone.shared import brick_blocks
from ..bone.tally import CONTACT_FIELDS, CONTACTS_KEPT
from .journal_format import (
    BRICKS,
    CONTACTS,
    LogScan,
    encode,
    file_header,
    read_bytes,
    scan,
    write_atomic,
)

BRICK_VOXELS = BRICK ** 3
BRICK_BYTES = 12 + 8 + BRICK_VOXELS
CONTACT_BYTES = 8 + CONTACT_FIELDS * 8
SIZES = {BRICKS: BRICK_BYTES, CONTACTS: CONTACT_BYTES}


#: Bricks per record (4.3 kB) and contacts per record: damage loses the records it touches,
#: so records stay small (their 16-byte headers cost 0.4 %).
RECORD_BRICKS = 8
RECORD_CONTACTS = 64


def records_of(n: int, per_record: int) -> int:
    """How many records ``n`` items take."""
    return -(-n // per_record)


def encode_bricks(index: np.ndarray, version: np.ndarray, swept: np.ndarray) -> bytes:
    """Brick records for bricks ``index`` (``RECORD_BRICKS`` a record)."""
    out = []
    for at in range(0, len(index), RECORD_BRICKS):
        part = slice(at, at + RECORD_BRICKS)
        payload = (np.ascontiguousarray(index[part], dtype="<i4").tobytes()
                   + np.ascontiguousarray(version[part], dtype="<i8").tobytes()
                   + np.ascontiguousarray(swept[part], dtype=np.uint8).tobytes())
        out.append(encode(BRICKS, len(index[part]), payload))
    return b"".join(out)


def encode_contacts(first: int, rows: np.ndarray) -> bytes:
    """Contact records for contacts ``first``… (``RECORD_CONTACTS`` a record)."""
    out = []
    for at in range(0, len(rows), RECORD_CONTACTS):
        part = rows[at:at + RECORD_CONTACTS]
        numbers = np.arange(first + at, first + at + len(part), dtype="<i8")
        payload = numbers.tobytes() + np.ascontiguousarray(part, dtype="<f8").tobytes()
        out.append(encode(CONTACTS, len(part), payload))
    return b"".join(out)


@dataclass
class LogContent:
    """A log as read: the latest record of every brick, every contact, and the scan.

    Attributes:
        index, version, swept: per brick (n, 3), (n,), (n, 8, 8, 8) (``read_log``).
        contacts: contact number → its row (time_s, x, y, z, label).
        scan: what was intact, damaged or cut short (``journal_format.LogScan``).
    """

    index: np.ndarray
    version: np.ndarray
    swept: np.ndarray
    contacts: dict[int, np.ndarray] = field(default_factory=dict)
    scan: LogScan = field(default_factory=LogScan)

    @property
    def contact_rows(self) -> tuple[int, np.ndarray]:
        """The contacts as a tally keeps them (``CarveTally.load``): (the number of the
        first, rows oldest first), at most ``CONTACTS_KEPT``. Numbers missing in the middle
        (damage) are closed up, so the count is of the contacts the log gives back; numbers
        below the lowest were dropped when the log was compacted and still count."""
        if not self.contacts:
            return 0, np.zeros((0, CONTACT_FIELDS))
        numbers = sorted(self.contacts)
        rows = np.stack([self.contacts[k] for k in numbers[-CONTACTS_KEPT:]])
        return numbers[0] + len(numbers) - len(rows), rows

    @property
    def contacts_begun(self) -> int:
        """Contacts counted once the log is replayed (``contact_rows``)."""
        first, rows = self.contact_rows
        return first + len(rows)


def read_carving(path: Path) -> LogContent:
    """Everything intact in the log at ``path`` (a missing file is an empty log)."""
    found = scan(read_bytes(path), SIZES)
    latest: dict[tuple[int, int, int], tuple[int, np.ndarray]] = {}
    contacts: dict[int, np.ndarray] = {}
    for kind, n, payload in found.records:
        if kind == CONTACTS:
            numbers = np.frombuffer(payload, "<i8", n)
            rows = np.frombuffer(payload, "<f8", n * CONTACT_FIELDS, n * 8).reshape(
                n, CONTACT_FIELDS)
            for k in range(n):
                contacts[int(numbers[k])] = rows[k].copy()
            continue
        index = np.frombuffer(payload, "<i4", n * 3).reshape(n, 3)
        version = np.frombuffer(payload, "<i8", n, n * 12)
        swept = np.frombuffer(payload, np.uint8, n * BRICK_VOXELS, n * 20).reshape(
            n, BRICK, BRICK, BRICK)
        for i in range(n):
            latest[tuple(index[i].tolist())] = (int(version[i]), swept[i])
    if not latest:
        return empty_log(contacts, found)
    keys = list(latest)
    return LogContent(np.array(keys, dtype=np.int32),
                      np.array([latest[k][0] for k in keys], np.int64),
                      np.stack([latest[k][1] for k in keys]), contacts, found)


def empty_log(contacts: dict[int, np.ndarray] | None = None,
              found: LogScan | None = None) -> LogContent:
    """A log with no bricks (and ``contacts``, if any)."""
    return LogContent(np.zeros((0, 3), np.int32), np.zeros(0, np.int64),
                      np.zeros((0, BRICK, BRICK, BRICK), np.uint8), contacts or {},
                      found or LogScan())


def read_log(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The latest record of every brick in the log: (index (n, 3), version (n,), swept
    (n, 8, 8, 8)). A missing file is an empty log."""
    content = read_carving(path)
    return content.index, content.version, content.swept


def check_fits(grid: BoneGrid, index: np.ndarray) -> None:
    """Raises ValueError if a brick of ``index`` lies outside ``grid`` (the log is for
    another bone)."""
    bshape = grid.brick_version.shape
    if len(index) and ((index < 0).any() or (index >= np.array(bshape)).any()):
        raise ValueError(f"the carve log has bricks outside this bone's {bshape} bricks: "
                         "its source changed since it was written")


def apply_log(grid: BoneGrid, index: np.ndarray, version: np.ndarray,
              swept: np.ndarray) -> int:
    """Write the records onto ``grid`` (a freshly loaded bone): its swept voxels, brick
    versions, version and brick summary. Returns the bricks written.

    Raises:
        ValueError: a brick lies outside the grid (the log is for another bone).
    """
    check_fits(grid, index)
    for n, (a, b, c) in enumerate(index.tolist()):
        block = grid.swept[a * BRICK:(a + 1) * BRICK, b * BRICK:(b + 1) * BRICK,
                           c * BRICK:(c + 1) * BRICK]
        block[...] = swept[n, :block.shape[0], :block.shape[1], :block.shape[2]]
        grid.brick_version[a, b, c] = version[n]
    if len(index):
        grid.version = max(grid.version, int(version.max()))
        grid.recount()
    return len(index)


def _key(index: np.ndarray) -> list[int]:
    return (index[:, 0].astype(np.int64) << 42 | index[:, 1].astype(np.int64) << 21
            | index[:, 2].astype(np.int64)).tolist()


class CarveLog:
    """Appends records to one session's log and compacts it when it has grown.

    Args:
        path: the log file.
        since_version: bricks stamped after this version are not in the log yet.
        log_id: the carving its header names (``journal_format``).
    """

    #: Compact when the file holds this many times the bytes of its latest records.
    COMPACT_RATIO = 4
    COMPACT_MIN_BYTES = 1 << 20

    def __init__(self, path: Path, since_version: int = 0, log_id: int = 0) -> None:
        self.path = path
        self.since_version = since_version
        self.log_id = log_id
        #: The bricks the log holds (what a compacted log would hold, known without reading
        #: it again); None until this object started or read the file.
        self._held: set[int] | None = None
        #: The highest brick stamp at the previous append (``append`` says why).
        self._last_max = -1
        self.size = 0
        self.records = 0
        #: Contacts logged: the number the next one has.
        self.contacts = 0
        #: The highest brick stamp the log holds.
        self.version = 0

    @property
    def bricks(self) -> int:
        return len(self._held or ())

    def start(self, content: LogContent | None = None, since_version: int = 0) -> None:
        """Write the log afresh (atomically): a header, then ``content``'s bricks and
        contacts (a resumed session's carving; None: a bone nobody cut yet)."""
        data = file_header(self.log_id)
        held: list[int] = []
        self.contacts = self.version = first_contact = 0
        if content is not None and len(content.index):
            data += encode_bricks(content.index, content.version, content.swept)
            held = _key(content.index)
            self.version = int(content.version.max())
        if content is not None and content.contacts:
            first_contact, rows = content.contact_rows
            data += encode_contacts(first_contact, rows)
            self.contacts = first_contact + len(rows)
        write_atomic(self.path, data)
        self._held = set(held)
        self.size = len(data)
        self.records = (records_of(len(held), RECORD_BRICKS)
                        + records_of(self.contacts - first_contact, RECORD_CONTACTS))
        self.since_version = since_version
        self._last_max = -1

    def reset(self, since_version: int) -> None:
        """A new bone: forget the records (its carving starts at ``since_version``)."""
        self.start(None, since_version)

    def append(self, swept: np.ndarray, brick_version: np.ndarray) -> int:
        """Write the bricks stamped after ``since_version``, read from live arrays (for a
        shared bone the journal takes them with ``SharedBone.carving_since`` instead);
        returns how many."""
        stamps = brick_version.copy()
        index = np.argwhere(stamps > self.since_version)
        return self.append_carving(index, stamps[tuple(index.T)],
                                   brick_blocks(swept, index), int(stamps.max(initial=0)))

    def append_carving(self, index: np.ndarray, version: np.ndarray, blocks: np.ndarray,
                       top: int, contacts: tuple[int, np.ndarray] | None = None) -> int:
        """Append the bricks ``index`` (stamped ``version``, voxels ``blocks``) and the
        contacts (first number, rows) not logged yet, in one write, and fsync; returns the
        bricks written. ``top``: the highest brick stamp of the bone now.

        Bricks of the highest stamp may belong to a tick still running (a tick stamps with
        the next version, and ticks that remove nothing reuse it), so they are written again
        at the next append unless that stamp was already the highest one then.

        Raises:
            OSError: the write failed (a full disk); the file is as it was before.
        """
        if self._held is None:
            self._open()
        rows = None
        if contacts is not None and contacts[0] + len(contacts[1]) > self.contacts:
            skip = max(0, self.contacts - contacts[0])
            rows = (contacts[0] + skip, contacts[1][skip:])
        if not len(index) and rows is None:
            return 0
        record = b""
        if len(index):
            record += encode_bricks(index, version, blocks)
        if rows is not None:
            record += encode_contacts(*rows)
        self._write(record)
        self.records += records_of(len(index), RECORD_BRICKS) + (
            records_of(len(rows[1]), RECORD_CONTACTS) if rows is not None else 0)
        if rows is not None:
            self.contacts = rows[0] + len(rows[1])
        if len(index):
            self.since_version = top if top == self._last_max else top - 1
            self._last_max = top
            self.version = max(self.version, int(version.max()))
            self._held.update(_key(index))  # type: ignore[union-attr]
        live = self.bricks * BRICK_BYTES + min(self.contacts, CONTACTS_KEPT) * CONTACT_BYTES
        if self.size >= self.COMPACT_MIN_BYTES and self.size > self.COMPACT_RATIO * live:
            self.start(read_carving(self.path), self.since_version)
        return len(index)

    def _write(self, record: bytes) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        try:
            start = os.lseek(fd, 0, os.SEEK_END)
            try:
                view = memoryview(record)
                while view:
                    view = view[os.write(fd, view):]
                os.fsync(fd)
            except OSError:
                os.ftruncate(fd, start)  # a full disk: no torn record for the next to follow
                raise
            self.size = start + len(record)
        finally:
            os.close(fd)

    def _open(self) -> None:
        """Take up a log this object did not start: a record a crash cut short is cut off
        (appending after it would hide what follows); a damaged log is kept aside and
        written afresh with what could be read."""
        content = read_carving(self.path)
        found = content.scan
        if found.damaged or found.header_damaged:
            keep_aside(self.path, "damaged")
            self.start(content, self.since_version)
            return
        if found.tail:
            os.truncate(self.path, found.end)
        elif found.size == 0:
            write_atomic(self.path, file_header(self.log_id))
            found.end = len(file_header(self.log_id))
        self._held = set(_key(content.index))
        self.size = found.end
        self.records = len(found.records)
        self.contacts = content.contacts_begun
        self.version = int(content.version.max()) if len(content.version) else 0


def keep_aside(path: Path, why: str) -> Path | None:
    """Keep ``path``'s bytes as ``<name>.<why>-<time>`` beside it, for a human (never
    deleted), before ``path`` is written afresh: a hard link (no space needed on a full
    disk), else a copy. Returns the name kept (None: no file, or it could not be kept)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    aside = path.with_name(f"{path.name}.{why}-{stamp}")
    n = 1
    while aside.exists():
        n += 1
        aside = path.with_name(f"{path.name}.{why}-{stamp}-{n}")
    if not path.exists():
        return None
    try:
        os.link(path, aside)
    except OSError:
        try:
            shutil.copy2(path, aside)
        except OSError:
            aside.unlink(missing_ok=True)
            return None
    return aside
