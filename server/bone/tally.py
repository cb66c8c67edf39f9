"""What a bone's cutting adds up to: the bone removed per label and the forbidden-structure
contacts begun, with the time, place and label of the latest ones.

The engine adds to a tally as it cuts. On a shared bone (``shared``) the tally lives in the
bone's file beside the voxels: a hot loop started again after a crash maps the same file and
counts on from where the killed one stopped, and the control plane reads it without asking the
loop (the journal, ``api.journal``, keeps it across a restart of the server). Elsewhere
(offline engines, replays) it is private memory.

Removal is counted in the carving kernels' units, density × swept steps (a voxel of density
255 swept from 0 to 255 is 255² units): integers, so sums are exact in float64, and the
removal of a set of voxels is also Σ density × (swept now − swept before) over them, which
is how a resumed session's tally is rebuilt from its replayed carving.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .bricks import BRICK
from .grid import BoneGrid

N_LABELS = 256
#: Forbidden contacts whose time, place and label are kept (the oldest are dropped first; the
#: count goes on).
CONTACTS_KEPT = 10_000
#: One kept contact, float64: time_s, x, y, z (world frame, mm), label.
CONTACT_FIELDS = 5
_COUNT_AT = N_LABELS * 8
_CONTACTS_AT = _COUNT_AT + 64


def tally_bytes(kept: int = CONTACTS_KEPT) -> int:
    """Bytes of a tally laid out in a buffer (``CarveTally.over``)."""
    return _CONTACTS_AT + kept * CONTACT_FIELDS * 8


@dataclass(frozen=True)
class ForbiddenContact:
    """The burr touched a forbidden structure (recorded when contact begins): when (s, on the
    clock the engine was given), where (world frame, mm), which label and material."""

    time_s: float
    position_mm: tuple[float, float, float]
    label: int
    material: str


class CarveTally:
    """Removal per label and forbidden contacts, over arrays that may be shared memory.

    Args:
        removed: float64 (N_LABELS,), removal per label in kernel units (written by the
            carving kernel in place).
        begun: int64 (1,), forbidden contacts begun.
        contacts: float64 (kept, CONTACT_FIELDS), a ring of the latest contacts.
    """

    def __init__(self, removed: np.ndarray, begun: np.ndarray, contacts: np.ndarray,
                 kept: int | None = None) -> None:
        self.removed = removed
        self._begun = begun
        self._contacts = contacts
        #: The most contacts kept: a private ring grows to it as contacts come.
        self._limit = len(contacts) if kept is None else kept

    @classmethod
    def private(cls, kept: int = CONTACTS_KEPT) -> CarveTally:
        """A tally in private memory, all zero, keeping up to ``kept`` contacts (its ring
        grows as they come: a replay may ask for no limit at all)."""
        return cls(np.zeros(N_LABELS), np.zeros(1, np.int64),
                   np.zeros((min(kept, 16), CONTACT_FIELDS)), kept)

    def _room(self, begun: int) -> np.ndarray:
        """The ring, grown (a private one) to hold ``begun`` contacts up to its limit. Until
        it is full contact k sits in slot k, so growing keeps every slot where it is."""
        ring = self._contacts
        if len(ring) < min(begun, self._limit):
            bigger = np.zeros((min(max(begun, 2 * len(ring)), self._limit), CONTACT_FIELDS))
            bigger[:len(ring)] = ring
            self._contacts = ring = bigger
        return ring

    @classmethod
    def over(cls, buffer, offset: int, kept: int = CONTACTS_KEPT) -> CarveTally:
        """A tally over ``buffer`` (an mmap, a bytearray) at byte ``offset``
        (``tally_bytes(kept)`` bytes; a read-only buffer gives a read-only tally)."""
        return cls(np.frombuffer(buffer, np.float64, N_LABELS, offset),
                   np.frombuffer(buffer, np.int64, 1, offset + _COUNT_AT),
                   np.frombuffer(buffer, np.float64, kept * CONTACT_FIELDS,
                                 offset + _CONTACTS_AT).reshape(kept, CONTACT_FIELDS))

    @property
    def begun(self) -> int:
        """Forbidden contacts begun since the bone was loaded (all, not only those kept)."""
        return int(self._begun[0])

    def add_contact(self, time_s: float, position_mm: tuple[float, float, float],
                    label: int) -> None:
        """One more contact begun (the ring slot first, then the count: a reader in another
        process that reads the count first never reads a slot not yet written)."""
        n = int(self._begun[0])
        ring = self._room(n + 1)
        if len(ring):
            ring[n % len(ring)] = (time_s, *position_mm, label)
        self._begun[0] = n + 1

    def rows_since(self, begun: int) -> tuple[int, np.ndarray]:
        """The kept contacts after the first ``begun``: (the number of the first one, a copy of
        their rows (m, CONTACT_FIELDS)), oldest first. Contacts older than the ring holds are
        skipped (the first number says how many)."""
        n = self.begun
        kept = len(self._contacts)
        first = max(begun, n - kept, 0)
        if first >= n:
            return n, np.zeros((0, CONTACT_FIELDS))
        slots = np.arange(first, n) % kept
        return first, self._contacts[slots].copy()

    def latest(self, n: int | None, name_of: Callable[[int], str]) -> list[ForbiddenContact]:
        """The latest ``n`` kept contacts (None: every kept one), oldest first, each named by
        ``name_of(label)``."""
        kept = min(self.begun, len(self._contacts))
        _, rows = self.rows_since(self.begun - (kept if n is None else min(n, kept)))
        return [ForbiddenContact(float(r[0]), (float(r[1]), float(r[2]), float(r[3])),
                                 int(r[4]), name_of(int(r[4]))) for r in rows]

    def load(self, removed: np.ndarray, begun: int, first: int, rows: np.ndarray) -> None:
        """Set the tally to what a journal kept: ``removed`` per label, ``begun`` contacts of
        which ``rows`` (oldest first) are numbers ``first``… (those beyond the ring's size are
        dropped, oldest first)."""
        self.removed[...] = removed
        ring = self._room(begun)
        kept = len(ring)
        rows = np.asarray(rows, dtype=np.float64).reshape(-1, CONTACT_FIELDS)
        numbers = np.arange(first, first + len(rows))
        keep = numbers >= begun - kept
        if kept:
            ring[numbers[keep] % kept] = rows[keep]
        self._begun[0] = begun

    def removed_mm3(self, voxel_volume_mm3: float) -> np.ndarray:
        """Removal per label, mm³ (float64 (N_LABELS,))."""
        return self.removed * (voxel_volume_mm3 / (255.0 * 255.0))


def removal_of(grid: BoneGrid, index: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """What writing bricks ``index`` (n, 3) with ``swept`` voxels ``blocks`` (n, 8, 8, 8)
    onto ``grid`` removes, per label, in the kernels' units (Σ density × (swept after −
    swept before)), float64 (N_LABELS,): a replayed carving's removal, exactly as the
    kernels counted it while cutting. Call before writing them."""
    out = np.zeros(N_LABELS)
    for n, (a, b, c) in enumerate(index.tolist()):
        sl = (slice(a * BRICK, (a + 1) * BRICK), slice(b * BRICK, (b + 1) * BRICK),
              slice(c * BRICK, (c + 1) * BRICK))
        old = grid.swept[sl]
        new = blocks[n, :old.shape[0], :old.shape[1], :old.shape[2]]
        delta = grid.density[sl].astype(np.float64) * (new.astype(np.float64) - old)
        out += np.bincount(grid.labels[sl].ravel(), weights=delta.ravel(), minlength=N_LABELS)
    return out
