"""A session's live state, in memory the control plane maps: telemetry without asking the loop.

The per-packet stages already keep everything a live view plots in two arrays per session
(``stages.new_state``): this packet's pose in the grid frame (W_P, W_AXIS, W_RPM, W_V), the
reply's floats (K_REPLY: force, resistive components, vibration...) and integers (M_REPLY:
seq, server times, status, bone version), and the model-stage times in ``Session.tick_ns``.
So the session allocates those arrays *inside* a file the control plane created and maps
read-only: the packet path runs the same code on the same array types, and the control
plane samples them at its own rate with no pipe, no lock and no work in the loop.

The file (one per session, created by the control plane, ``api.telemetry``): a header page of
int64 (magic; the number of installs and the active slot in one word, so that a reader never
pairs one install's count with another's slot), then two slots, each page-aligned:
the grid's geometry (float64 (SLOT_GEOMETRY,): origin_mm (3), direction (9) row-major), ``k``
(float64 (K_SIZE,)), ``m`` (int64 (M_SIZE,)) and the tick-time ring (int64
(TICK_TIMES_KEPT,), ns). Two slots, because a session is built and warmed up (which ticks it)
while the one it replaces still streams: the new one is built in the other slot, and
:meth:`TelemetrySlot.activate` switches the header to it when it is installed, between two
packets.

Torn reads are accepted, not prevented: the loop bumps no counter per packet (the shared
bone's seqlock brackets carving ticks only), and adding one would be work per packet. A
reader copies the slot and re-checks the reply's (seq, t_recv) around the copy (``api.
telemetry``), which catches a reply written meanwhile; what it cannot catch is the next
packet's pose (written first, by ``pose_in``) next to the previous packet's reply, one sample
in a plot.
"""

from __future__ import annotations

import mmap
import os
from pathlib import Path

import numpy as np

from .stages import K_REPLY, K_SIZE, M_REPLY, M_SIZE, W_LAST_FORCE, W_P, W_RPM
from .wire import REPLY_FLOATS, REPLY_INTS

#: Model-stage times kept per session for statistics (a ring buffer, ``Session.tick_ns``):
#: in a slot here, or in private memory for a session without a telemetry file.
TICK_TIMES_KEPT = 8192
PAGE = 4096
MAGIC = 0x6275727274656C31  # "burrtel1"
#: Header slots (int64).
H_MAGIC = 0
#: ``installs * 2 + slot``: sessions installed so far (0: none yet: nothing to read) and the
#: slot the installed one writes (0 or 1), written with one 8-byte store.
H_STATE = 1
N_HEADER = 8


SLOTS = 2
#: A slot's geometry (float64): the grid frame in the server frame.
G_ORIGIN = 0  #: (3) mm
G_DIRECTION = 3  #: (9) row-major, the grid's axes as columns (``BoneGrid.direction``)
SLOT_GEOMETRY = 12


def installs_and_slot(state: int) -> tuple[int, int]:
    """``(installs, active slot)`` from the header's ``H_STATE`` word."""
    return state >> 1, state & 1


def _align(n: int) -> int:
    return (n + PAGE - 1) // PAGE * PAGE


#: Byte offsets inside a slot.
_GEOMETRY_AT = 0
_K_AT = _GEOMETRY_AT + SLOT_GEOMETRY * 8
_M_AT = _K_AT + K_SIZE * 8
_TICKS_AT = _M_AT + M_SIZE * 8
SLOT_BYTES = _align(_TICKS_AT + TICK_TIMES_KEPT * 8)
FILE_BYTES = PAGE + SLOTS * SLOT_BYTES


def create(path: str | os.PathLike) -> None:
    """A zeroed telemetry file at ``path`` (replaced if there is one): no session yet."""
    tmp = Path(f"{path}.tmp")
    with open(tmp, "wb") as f:
        f.truncate(FILE_BYTES)
        # Every page reserved now: the hot loop writing through its map of a full tmpfs
        # would be a SIGBUS (as for shared bones); here it is an OSError in the caller.
        os.posix_fallocate(f.fileno(), 0, FILE_BYTES)
        f.write(np.array([MAGIC], np.int64).tobytes())
    os.replace(tmp, path)


def slot_arrays(buf: mmap.mmap | bytes | bytearray | memoryview,
                slot: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(geometry float64 (SLOT_GEOMETRY,), k float64 (K_SIZE,), m int64 (M_SIZE,),
    tick_ns int64 (TICK_TIMES_KEPT,))`` of slot ``slot`` over ``buf`` (a map or a copy)."""
    at = PAGE + slot * SLOT_BYTES
    return (np.frombuffer(buf, np.float64, SLOT_GEOMETRY, at + _GEOMETRY_AT),
            np.frombuffer(buf, np.float64, K_SIZE, at + _K_AT),
            np.frombuffer(buf, np.int64, M_SIZE, at + _M_AT),
            np.frombuffer(buf, np.int64, TICK_TIMES_KEPT, at + _TICKS_AT))


def header(buf: mmap.mmap | bytes | bytearray | memoryview) -> np.ndarray:
    """The header, int64 (N_HEADER,)."""
    return np.frombuffer(buf, np.int64, N_HEADER, 0)


class TelemetrySlot:
    """The hot loop's side: a session's state arrays in a telemetry file.

    Built on a file, it takes the slot the installed session does not write; the session is built
    on its arrays (``Session(..., telemetry=slot)``); :meth:`activate` makes it the one the
    control plane reads, once the session is installed (under the loop's lock).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        with open(path, "r+b") as f:
            self._map = mmap.mmap(f.fileno(), FILE_BYTES, access=mmap.ACCESS_WRITE)
        self._header = header(self._map)
        if int(self._header[H_MAGIC]) != MAGIC:
            raise ValueError(f"{path} is not a telemetry file")
        installs, active = installs_and_slot(int(self._header[H_STATE]))
        self.slot = 1 - active if installs > 0 else 0
        self.geometry, self.k, self.m, self.tick_ns = slot_arrays(self._map, self.slot)
        for a in (self.geometry, self.k, self.m, self.tick_ns):
            a[:] = 0

    def activate(self, origin_mm: np.ndarray, direction: np.ndarray) -> None:
        """Make this slot the one read: the grid's ``origin_mm`` (3,) and ``direction`` (3, 3)
        go in, and what warming the session up left in the pose, the reply and the tick ring
        is cleared (a reply seq and t_recv of 0: no packet yet). The pose values (W_P to
        W_RPM) are outputs of ``pose_in``, not state carried across packets."""
        self.geometry[G_ORIGIN:G_ORIGIN + 3] = origin_mm
        self.geometry[G_DIRECTION:G_DIRECTION + 9] = np.asarray(direction).ravel()
        self.k[W_P:W_RPM + 1] = 0.0
        self.k[K_REPLY:K_REPLY + REPLY_FLOATS] = 0.0
        self.k[W_LAST_FORCE] = 0.0
        self.m[M_REPLY:M_REPLY + REPLY_INTS] = 0
        self.tick_ns[:] = 0
        installs, _ = installs_and_slot(int(self._header[H_STATE]))
        self._header[H_STATE] = (installs + 1) * 2 + self.slot
