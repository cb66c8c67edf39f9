"""The journal's log framing: a file header, then records, each checked by its own CRC-32, and
a reader that keeps every record it can prove intact and says what it could not read.

Format 2 (little-endian)::

    file header, 20 bytes:
        magic       b"BFJL"
        version     uint32   2
        log id      uint64   names the bone's carving this log is for: ``session.json``
                             names it too (``carve_log``), so a log left from the bone
                             before a reset or a new load is never replayed onto the new one
        crc         uint32   CRC-32 of the 16 bytes before it
    records, one after the other:
        kind        4 bytes  b"BFCR" (carved bricks) or b"BFCT" (forbidden contacts)
        n           uint32   items in the record
        length      uint32   bytes of the payload that follows
        crc         uint32   CRC-32 of kind, n and length, then of the payload
        payload     ``length`` bytes (``journal_carve`` says what each kind holds)

Format 1, what releases before format 2 wrote, has no file header and only brick records,
whose CRC covers the payload alone; it is read as it is (``scan`` accepts either CRC).

A record that fails its check is skipped, not the end of the log: the reader looks for the
next record that passes its own and goes on from there, so damage in the middle of a log loses
only what the damaged bytes held. The bytes skipped are reported (``LogScan.damaged``).
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from ..whole_files import WholeFile

FILE_MAGIC = b"BFJL"
FILE_VERSION = 2
BRICKS = b"BFCR"
CONTACTS = b"BFCT"
KINDS = (BRICKS, CONTACTS)
_FILE_HEAD = struct.Struct("<4sIQI")
_RECORD_HEAD = struct.Struct("<4sIII")
FILE_HEAD_BYTES = _FILE_HEAD.size
RECORD_HEAD_BYTES = _RECORD_HEAD.size


def file_header(log_id: int) -> bytes:
    """A format-2 log's first bytes, for the carving ``log_id`` names."""
    head = struct.pack("<4sIQ", FILE_MAGIC, FILE_VERSION, int(log_id))
    return head + struct.pack("<I", zlib.crc32(head))


def encode(kind: bytes, n: int, payload: bytes) -> bytes:
    """One format-2 record."""
    crc = zlib.crc32(payload, zlib.crc32(struct.pack("<4sII", kind, n, len(payload))))
    return _RECORD_HEAD.pack(kind, n, len(payload), crc) + payload


@dataclass
class LogScan:
    """What ``scan`` read of a log.

    Attributes:
        version: 2 with an intact format-2 header, 1 without one (a format-1 log, or a
            format-2 log whose header is damaged: ``header_damaged``), 0 for an empty file.
        log_id: the carving the header names (None: no intact header).
        records: (kind, n, payload) of every intact record, in file order.
        damaged: (offset, bytes) of each run of bytes that is no intact record and is
            followed by one (damage, not a crash's torn end).
        tail: bytes after the last intact record that are no record (a record a crash cut
            short, or damage at the end).
        end: where the last intact record ends (the header's end if there is none).
        size: the file's length, bytes.
    """

    version: int = 0
    log_id: int | None = None
    header_damaged: bool = False
    records: list[tuple[bytes, int, bytes]] = field(default_factory=list)
    damaged: list[tuple[int, int]] = field(default_factory=list)
    tail: int = 0
    end: int = 0
    size: int = 0

    @property
    def damaged_bytes(self) -> int:
        return sum(n for _, n in self.damaged)


def _record_at(data: bytes, at: int, sizes: dict[bytes, int]) -> tuple[bytes, int, bytes] | None:
    """The intact record at ``at`` or None. ``sizes``: bytes per item of each kind (a record
    whose length is not n items is not intact whatever its CRC)."""
    if at + RECORD_HEAD_BYTES > len(data):
        return None
    kind, n, length, crc = _RECORD_HEAD.unpack_from(data, at)
    if kind not in sizes or length != n * sizes[kind]:
        return None
    start = at + RECORD_HEAD_BYTES
    if start + length > len(data):
        return None
    payload = data[start:start + length]
    body = zlib.crc32(payload)
    if crc != body and crc != zlib.crc32(payload, zlib.crc32(data[at:at + 12])):
        return None  # neither format 2's CRC (header and payload) nor format 1's (payload)
    return kind, n, payload


def scan(data: bytes, sizes: dict[bytes, int]) -> LogScan:
    """Every intact record of ``data`` (a whole log file), skipping over damage."""
    out = LogScan(size=len(data))
    at = 0
    if data[:4] == FILE_MAGIC and len(data) >= FILE_HEAD_BYTES:
        _, version, log_id, crc = _FILE_HEAD.unpack_from(data, 0)
        if crc == zlib.crc32(data[:16]):
            out.version, out.log_id = version, log_id
            at = FILE_HEAD_BYTES
    if out.version == 0 and data:
        out.version = 1
        # Format 1 starts with a record: anything else there is a damaged header.
        out.header_damaged = _record_at(data, 0, sizes) is None
    out.end = at
    bad_from = None
    while at < len(data):
        record = _record_at(data, at, sizes)
        if record is None:
            if bad_from is None:
                bad_from = at
            at = _next_magic(data, at + 1)
            continue
        if bad_from is not None:
            out.damaged.append((bad_from, at - bad_from))
            bad_from = None
        out.records.append(record)
        at += RECORD_HEAD_BYTES + len(record[2])
        out.end = at
    if bad_from is not None:
        out.tail = len(data) - bad_from
    return out


def _next_magic(data: bytes, start: int) -> int:
    """Where the next record kind's magic starts at or after ``start`` (or the end)."""
    found = [i for i in (data.find(kind, start) for kind in KINDS) if i >= 0]
    return min(found) if found else len(data)


def read_bytes(path: Path) -> bytes:
    """A log's bytes; a missing file reads as empty."""
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return b""


def write_atomic(path: Path, data: bytes, mode: int = 0o600) -> None:
    """Replace ``path`` with ``data`` so that a crash leaves the old or the new file, never
    a mix (``whole_files.WholeFile``: a temporary file, fsync, rename, the folder synced). A
    write that fails (a full disk: ``DiskFull``) removes its temporary file and leaves
    ``path`` as it was. The temporary name is fixed (``NAME.tmp``): one writer per journal
    file, and a crash's leftover is overwritten by the next write rather than piling up."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with WholeFile(path, permissions=mode, part_name=path.name + ".tmp") as f:
        f.write(data)
