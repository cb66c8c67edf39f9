"""A session's journal state (``state.bin``): what its bone looked like at the journal's latest
pass and how much of it the carve log holds — the yardstick a restart measures what it lost
against.

Written at every pass, in place, into a file made at its full size when the bone was loaded,
so that it can still be written when the disk is full and the carve log cannot (overwriting
blocks a file already has needs no new ones on ext4, xfs or tmpfs). Two slots take turns; each
holds a sequence number, its JSON and a CRC-32 over both, so a write cut short by a crash
leaves the other slot, one pass older, to read::

    slot (SLOT_BYTES, two of them):
        magic b"BFST" | format uint32 (1) | sequence uint64 | length uint32 | crc uint32
        | JSON (length bytes) | zero padding

The JSON (``JournalState.as_json``) holds the carve log's id, the live tally (bone version,
removal per label in the kernels' units, contacts begun) and what the log held then (bytes,
records, bricks, highest stamp, contacts), the bricks stamped after that, and since when the
log could not be written (null while it can).
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .journal_format import write_atomic

MAGIC = b"BFST"
FORMAT = 1
SLOT_BYTES = 16384
SLOTS = 2
_HEAD = struct.Struct("<4sIQII")


@dataclass
class JournalState:
    """One pass of the journal over a session's bone (see the module's docstring).

    Attributes:
        log_id: the carving it is for (the carve log's id, ``journal_format``).
        t: when, Unix time, s.
        bone_version: the bone's version then.
        removed: removal per label (kernel units, integral), only labels that lost bone.
        contacts: forbidden contacts begun.
        log: what the carve log held: bytes, records, bricks, version, contacts.
        unlogged_bricks: bricks stamped after the log's last record.
        behind_since: Unix time since which the log could not be written (None: it can).
        error: why not.
    """

    log_id: int
    t: float
    bone_version: int
    removed: dict[str, float]
    contacts: int
    log: dict = field(default_factory=dict)
    unlogged_bricks: int = 0
    behind_since: float | None = None
    error: str | None = None

    def as_json(self) -> bytes:
        return json.dumps(asdict(self), separators=(",", ":"), sort_keys=True).encode()

    @classmethod
    def from_json(cls, data: bytes) -> JournalState:
        raw = json.loads(data)
        return cls(**{k: raw[k] for k in cls.__dataclass_fields__ if k in raw})


class StateFile:
    """Writes ``state.bin`` in place (``create`` once per bone, then ``write`` every pass)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sequence = 0

    def _slot(self, state: JournalState) -> bytes:
        body = state.as_json()
        if _HEAD.size + len(body) > SLOT_BYTES:
            raise ValueError(f"journal state of {len(body)} bytes does not fit a slot")
        head = struct.pack("<4sIQI", MAGIC, FORMAT, self.sequence, len(body))
        return head + struct.pack("<I", zlib.crc32(body, zlib.crc32(head))) + body

    def create(self, state: JournalState) -> None:
        """A new file holding ``state``, at its full size (real blocks, not a sparse file:
        later writes then need no new ones), replacing any older one atomically.

        Raises:
            OSError: it could not be written (a full disk); an older file is left as it was.
        """
        self.sequence = 1
        image = bytearray(SLOT_BYTES * SLOTS)
        slot = self._slot(state)
        at = (self.sequence % SLOTS) * SLOT_BYTES
        image[at:at + len(slot)] = slot
        write_atomic(self.path, bytes(image))

    def write(self, state: JournalState) -> None:
        """Overwrite the older slot with ``state`` and fdatasync. Raises OSError."""
        self.sequence += 1
        slot = self._slot(state)
        fd = os.open(self.path, os.O_WRONLY)
        try:
            os.pwrite(fd, slot, (self.sequence % SLOTS) * SLOT_BYTES)
            os.fdatasync(fd)
        finally:
            os.close(fd)


def read_state(path: Path) -> JournalState | None:
    """The latest intact slot of ``path`` (None: no file, or no intact slot)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    best: tuple[int, JournalState] | None = None
    for k in range(SLOTS):
        slot = data[k * SLOT_BYTES:(k + 1) * SLOT_BYTES]
        if len(slot) < _HEAD.size:
            continue
        magic, _, sequence, length, crc = _HEAD.unpack_from(slot, 0)
        body = slot[_HEAD.size:_HEAD.size + length]
        if (magic != MAGIC or len(body) != length
                or crc != zlib.crc32(body, zlib.crc32(slot[:_HEAD.size - 4]))):
            continue
        try:
            state = JournalState.from_json(body)
        except (ValueError, TypeError, KeyError):
            continue
        if best is None or sequence > best[0]:
            best = (sequence, state)
    return best[1] if best is not None else None
