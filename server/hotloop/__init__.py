"""The UDP hot loop: sessions, the protocol in front of them, and the process that runs them.

Rooms, lower first: ``errors`` (how a command fails, as data), ``bucket``, ``wire`` and
``stages`` (the per-packet kernels), ``telemetry`` (a session's state in a mapped file),
``session_config`` and ``session`` (one engine's burr on one bone), ``dispatch`` (decode → tag
→ order → tick → encode), ``wake`` and ``loop`` (the socket loop), ``spec`` (what a worker
runs), ``commands`` (the command table), ``child`` (the loop process's main), ``handle``
(``HotLoopProcess``, the parent's side) and ``pool`` (many workers).
"""

from .dispatch import Dispatcher
from .handle import HotLoopProcess
from .session import Session
from .session_config import SessionConfig
from .spec import DEFAULT_BONE, HotLoopConfig, SessionSpec, build_session

__all__ = ["DEFAULT_BONE", "Dispatcher", "HotLoopConfig", "HotLoopProcess", "Session",
           "SessionConfig", "SessionSpec", "build_session"]
