"""Devices attached to sessions: one device loop process per session, at most."""

from __future__ import annotations

import threading

from ..devices.loop import DeviceLoopConfig
from ..devices.process import DeviceProcess
from .errors import Conflict, Invalid, NotFound
from .sessions import ManagedSession

#: How long an attach waits for the loop to open its device (homing continues after).
OPEN_WAIT_S = 10.0


class DeviceAttachments:
    """The device loops of a control plane, by session id (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.loops: dict[int, DeviceProcess] = {}

    def attach(self, session: ManagedSession, address: tuple[str, int],
               make_config) -> DeviceProcess:
        """Start a device loop for a ready session whose hot loop listens on ``address``.
        ``make_config(session, host, port)`` returns its DeviceLoopConfig (ValueError →
        Invalid). Waits until the device is open (or homing); a loop that fails to open is
        removed and its reason raised as Invalid (the request names a device this machine
        cannot open: not plugged in, no permission, a vendor library or firmware missing).
        Conflict: the session drives a device already."""
        session_id = session.id
        host, port = address
        if host in ("0.0.0.0", "::", ""):
            host = "127.0.0.1" if host != "::" else "::1"
        try:
            config: DeviceLoopConfig = make_config(session, host, port)
        except ValueError as exc:
            raise Invalid(str(exc)) from None
        with self._lock:
            old = self.loops.get(session_id)
            # A loop being attached (not started yet) holds its slot as much as a running one.
            if old is not None and (old.started_s is None or old.is_alive()):
                raise Conflict(f"session {session_id} already drives {old.config.device}; "
                               "DELETE its device first")
            process = DeviceProcess(config)
            self.loops[session_id] = process
        if old is not None:
            old.stop()  # a loop that ended by itself (failed, unplugged): release it
        process.start()
        state = process.wait_state(("homing", "running", "stopped", "failed"), OPEN_WAIT_S)
        if state in ("failed", "stopped"):
            process.stop()
            reasons = [text for _, text in process.events if text.startswith("failed")]
            with self._lock:
                if self.loops.get(session_id) is process:
                    del self.loops[session_id]
            raise Invalid(reasons[-1] if reasons else f"the device loop {state}")
        return process

    def get(self, session_id: int) -> DeviceProcess:
        with self._lock:
            process = self.loops.get(session_id)
        if process is None:
            raise NotFound(f"session {session_id} has no device attached")
        return process

    def detach(self, session_id: int) -> dict:
        with self._lock:
            process = self.loops.pop(session_id, None)
        if process is None:
            raise NotFound(f"session {session_id} has no device attached")
        process.stop()
        return process.status()

    def attached(self, session_id: int) -> bool:
        """Whether a device loop runs (or is starting) for the session."""
        with self._lock:
            process = self.loops.get(session_id)
        return process is not None and (process.started_s is None or process.is_alive())

    def discard(self, session_id: int) -> None:
        """Stop the session's device loop, if it has one."""
        with self._lock:
            process = self.loops.pop(session_id, None)
        if process is not None:
            process.stop()

    def statuses(self) -> dict[int, dict]:
        with self._lock:
            loops = dict(self.loops)
        return {sid: p.status() for sid, p in loops.items()}

    def close(self) -> None:
        with self._lock:
            loops = list(self.loops.values())
            self.loops.clear()
        for process in loops:
            process.stop()
