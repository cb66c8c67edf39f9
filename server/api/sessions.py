"""Sessions as the user configured them over REST, and the table that holds them.

The hot loop owns the live sessions; this side keeps what each session *should* be: its bone
source, its :class:`Settings` (cutting parameters, shaft, vibration, frame, features, device,
materials) and its shared bone. A feature turned off becomes a setting the loop skips (no
shaft: a zero-length shaft; no vibration: no vibration parameters):
:meth:`Settings.effective_config` and :meth:`Settings.effective_shaft` are what the loop is
sent.

:class:`SessionTable` is the only owner of the id → session map; every other service reads
it through its methods (copies taken under its lock), never through a lock of its own.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import TypeVar

from ..bone import Bone, MaterialTable, ShaftParams
from ..bone.grid import BoneGrid
from ..bone.shared import SharedBone, SharedBoneRef
from ..bone.tally import CarveTally
from ..haptics import DeviceProfile, HapticsConfig
from ..hotloop import SessionConfig
from ..model.params import CuttingParams
from ..model.vibration import VibrationParams
from .errors import Busy, Conflict, Invalid, NotFound, Unavailable
from .journal_status import JournalStatus
from .models import Features
from .sources import BoneSource

T = TypeVar("T")


@dataclass(frozen=True)
class Settings:
    """What a session computes with, as one value: the parameter service builds a new one
    (validated) and the session takes it whole (``session.settings = new``) once the hot
    loop has accepted it, so a refused change leaves nothing half applied.

    ``overrides``: material changes made over REST, per label (None: the primary material),
    applied again to every bone the session loads (a reset keeps the user's Us and K).
    """

    params: CuttingParams
    shaft: ShaftParams
    vibration: VibrationParams
    config: SessionConfig
    features: Features
    device: DeviceProfile | None = None
    materials: MaterialTable | None = None
    primary_label: int | None = None
    overrides: dict = field(default_factory=dict)

    def effective_config(self) -> SessionConfig:
        """The loop's session configuration, features applied (vibration off: none)."""
        f = self.features
        output = None if f.coupling is None else ("coupled" if f.coupling else "raw")
        return replace(self.config, model=f.model, carve=f.carving,
                       vibration=self.vibration if f.vibration else None,
                       haptics=HapticsConfig.for_device(self.device, output))

    def effective_shaft(self) -> ShaftParams:
        """The shaft the loop computes (shaft off: zero length)."""
        return self.shaft if self.features.shaft else replace(self.shaft, length_mm=0.0)


class _Setting:
    """A session attribute that is one field of its :attr:`ManagedSession.settings`: read
    from them, and set by replacing them (a new :class:`Settings` with that field changed)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, session: ManagedSession | None, owner: type | None = None) -> object:
        if session is None:
            return self
        return getattr(session.settings, self.name)

    def __set__(self, session: ManagedSession, value: object) -> None:
        session.settings = replace(session.settings, **{self.name: value})


@dataclass
class ManagedSession:
    """One session as configured over REST. Its settings are one :class:`Settings` value
    (``settings``), each field also readable and settable as the session's own attribute
    (``session.params``, ``session.materials``, …)."""

    id: int
    key_hex: str | None
    source: BoneSource
    settings: Settings
    bone_info: dict | None = None
    ref: SharedBoneRef | None = None
    reader: SharedBone | None = None
    #: An open descriptor of the shared bone file (its name is unlinked once the loop maps
    #: it): what lets a restarted hot loop map the same, carved memory again.
    bone_fd: int | None = None
    state: str = "loading"  # loading | ready | failed
    error: str | None = None
    job_id: str | None = None
    in_loop: bool = False
    #: The index of the hot-loop worker the session runs on, for life (``WorkerPool.place``).
    worker: int = 0
    recording: dict | None = None
    #: The first stream number the next hot loop offers (None: a random one).
    next_stream: int | None = None
    #: Applied once to the next bone loaded, before it is shared: a resumed session's
    #: carving (``journal``); what it returns is the bone's tally (``bone.tally``).
    pending_carve: Callable[[Bone], CarveTally | None] | None = None
    #: How its journal stands (written, degraded, what a resume lost).
    journal: JournalStatus = field(default_factory=JournalStatus)
    #: What the hot loop was last sent (params, shaft, config, publish).
    sent: dict = field(default_factory=dict)
    #: Calibrations applied over REST: material label → the latest record.
    calibrations: dict = field(default_factory=dict)
    created_s: float = field(default_factory=time.time)
    #: Serializes changes to this session (loads, parameters, recordings).
    lock: threading.RLock = field(default_factory=threading.RLock)

    params = _Setting()
    shaft = _Setting()
    vibration = _Setting()
    config = _Setting()
    features = _Setting()
    device = _Setting()
    materials = _Setting()
    primary_label = _Setting()
    overrides = _Setting()

    def effective_config(self) -> SessionConfig:
        return self.settings.effective_config()

    def effective_shaft(self) -> ShaftParams:
        return self.settings.effective_shaft()

    @property
    def output(self) -> str:
        """The output the session renders: raw or coupled."""
        return self.effective_config().haptics.output

    def snapshot_bone(self) -> Bone:
        """A consistent private copy of the session's bone as it is now, with its materials.

        Raises:
            Conflict: deltas are off (the loop does not publish the bone while it is cut).
            Unavailable: the loop held a carving tick open too long.
        """
        if not self.features.deltas:
            raise Conflict("the session has deltas off: the loop does not publish the bone "
                           "while it is cut; turn the feature on first")
        reader = self.reader
        assert reader is not None
        try:
            bone = reader.snapshot()
        except TimeoutError as exc:
            raise Unavailable(str(exc)) from None
        bone.materials = self.materials.copy() if self.materials else bone.materials
        return bone


    def read_bone(self, read: Callable[[BoneGrid], T]) -> T:
        """What ``read`` makes of the bone the loop last published (``SharedBone``'s
        ``read_published``; deltas on).

        Raises:
            Invalid: ``read`` refused its arguments (a ValueError).
            Unavailable: the loop held a carving tick open too long.
        """
        reader = self.reader
        assert reader is not None
        try:
            return reader.read_published(read)
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        except TimeoutError as exc:
            raise Unavailable(str(exc)) from None

class SessionTable:
    """Sessions by id; thread-safe. Reads return copies taken under the table's lock, so a
    caller never iterates a map that changes meanwhile.

    Args:
        limit: the most sessions it holds (``ServeConfig.max_sessions``).
    """

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._by_id: dict[int, ManagedSession] = {}
        self._lock = threading.RLock()

    def __len__(self) -> int:
        return len(self._by_id)

    def __contains__(self, session_id: object) -> bool:
        return session_id in self._by_id

    def __iter__(self) -> Iterator[int]:
        return iter(self.keys())

    def __getitem__(self, session_id: int) -> ManagedSession:
        with self._lock:
            return self._by_id[session_id]

    def keys(self) -> list[int]:
        with self._lock:
            return list(self._by_id)

    def values(self) -> list[ManagedSession]:
        with self._lock:
            return list(self._by_id.values())

    def items(self) -> list[tuple[int, ManagedSession]]:
        with self._lock:
            return list(self._by_id.items())

    def get(self, session_id: int | None, default: ManagedSession | None = None
            ) -> ManagedSession | None:
        """The session, or ``default`` (no error)."""
        with self._lock:
            return self._by_id.get(session_id, default)  # type: ignore[arg-type]

    def find(self, session_id: int) -> ManagedSession:
        """The session; :class:`NotFound` if there is none."""
        session = self.get(session_id)
        if session is None:
            raise NotFound(f"no session {session_id}")
        return session

    def ready(self, session_id: int) -> ManagedSession:
        """The session if its bone is loaded; :class:`Conflict` while it loads or failed."""
        session = self.find(session_id)
        if session.state != "ready":
            raise Conflict(f"session {session_id} is {session.state}"
                           + (f": {session.error}" if session.error else "")
                           + (f" (job {session.job_id})" if session.state == "loading"
                              else ""))
        return session

    def register(self, session: ManagedSession, session_id: int | None,
                 place: Callable[[list[ManagedSession]], int]) -> ManagedSession:
        """Add ``session`` under ``session_id`` (None: the lowest free id ≥ 1), on the worker
        ``place`` picks from the sessions there are (it runs under the lock, so two new
        sessions never see the same load).

        Raises:
            Busy: the table holds its ``limit``.
            Conflict: ``session_id`` is in use.
        """
        with self._lock:
            if len(self._by_id) >= self.limit:
                raise Busy(f"the server holds its maximum of {self.limit} sessions "
                           "(max_sessions): delete one first")
            if session_id is None:
                session_id = next(i for i in range(1, 1 << 32) if i not in self._by_id)
            elif session_id in self._by_id:
                raise Conflict(f"session {session_id} exists")
            session.id = session_id
            session.worker = place(list(self._by_id.values()))
            self._by_id[session_id] = session
        return session

    def remove(self, session_id: int, then: Callable[[], None] | None = None) -> None:
        """Forget the session; ``then`` runs under the lock too (before a new session may
        take the id)."""
        with self._lock:
            self._by_id.pop(session_id, None)
            if then is not None:
                then()

    def on_worker(self, index: int) -> list[int]:
        """The ids of the sessions placed on worker ``index``."""
        return sorted(s.id for s in self.values() if s.worker == index)

    def clear(self) -> None:
        with self._lock:
            self._by_id.clear()
