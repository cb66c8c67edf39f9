"""What a hot-loop process is started with (:class:`HotLoopConfig`), apart from the sessions'
own specs (``spec``): light to import, so a parent spawns its loops before it imports the
bone, numba and the web stack."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from .wake import DEFAULT_WAKE, WakeConfig

if TYPE_CHECKING:
    from .spec import SessionSpec

#: The first message to a spare (``HotLoopProcess.spawn_spare``) instead of a
#: ``HotLoopConfig``: warm up, then wait for the config.
STANDBY = "standby"


@dataclass(frozen=True)
class HotLoopConfig:
    """Where the hot loop listens, the sessions it starts with, whether it wakes ahead of
    its streams' packets (``hotloop.wake``), and whether its loop thread asks for the
    real-time scheduler (``server.realtime``; it then blocks for each datagram instead of
    waking ahead).

    ``restoring``: the ids of sessions the control plane is about to add back after a
    restart (``api.supervisor``). Their datagrams are held, unanswered, until each is back
    (then its client hears WRONG_STREAM once and says hello) or the command ``restored``
    says the restore is over; never UNKNOWN_SESSION, which a client takes for a session that
    is gone."""

    host: str = "127.0.0.1"
    udp_port: int = 0
    sessions: tuple[SessionSpec, ...] = ()
    wake: WakeConfig = DEFAULT_WAKE
    realtime: bool = False
    restoring: tuple[int, ...] = ()
