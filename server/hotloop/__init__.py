"""The UDP hot loop: sessions, the protocol in front of them, and the process that runs them."""

from .dispatch import Dispatcher
from .process import DEFAULT_BONE, HotLoopConfig, HotLoopProcess, SessionSpec, build_session
from .session import Session, SessionConfig

__all__ = ["DEFAULT_BONE", "Dispatcher", "HotLoopConfig", "HotLoopProcess", "Session",
           "SessionConfig", "SessionSpec", "build_session"]
