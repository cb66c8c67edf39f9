"""Recording a session's stream: started, queried and stopped here, written by its hot loop.

A recording starts from a snapshot of the session's bone (``record.format.SNAPSHOT_NAME``) in
a new ``.burrrec`` folder of the data directory; the loop then appends the poses, engine
inputs, forces and removals, capped by the room left in the data budget and on the disk
(``Storage.recording_cap``) so it stops cleanly there. Raises the domain errors of
``errors``.
"""

from __future__ import annotations

import shutil
import time

from ..bone.loaders import save_bone
from ..record.format import SNAPSHOT_NAME
from ..whole_files import DiskFull
from .errors import Conflict
from .sessions import ManagedSession
from .storage import Storage
from .workers import WorkerPool


class Recordings:
    """Starts and stops the sessions' recordings (the state is each session's
    ``recording``)."""

    def __init__(self, pool: WorkerPool, storage: Storage) -> None:
        self.pool = pool
        self.storage = storage

    def start(self, session: ManagedSession, name: str | None, max_bytes: int) -> dict:
        """Record ``session`` (ready) from now on into recording ``name`` (None: one named
        after the session and the time), at most ``max_bytes`` of chunks.

        Raises:
            Conflict: the session records already, or the recording exists.
            NoRoom: the data budget or the disk is full (nothing of the recording is kept).
            Unavailable: the loop cannot start it.
        """
        with session.lock:
            if session.recording is not None:
                raise Conflict(f"session {session.id} is already recording "
                               f"({session.recording['name']})")
            bone = session.snapshot_bone()
            name = name or f"session-{session.id}-{time.strftime('%Y%m%d-%H%M%S')}"
            path = self.storage.new_recording_dir(name)
            try:
                try:
                    save_bone(bone, path / SNAPSHOT_NAME)
                except DiskFull as exc:
                    raise self.storage.disk_filled(exc, "the recording's start snapshot"
                                                   ) from None
                # Capped by the room left in the budget and on the disk, so it stops cleanly
                # there instead of failing on a full disk.
                max_bytes = self.storage.recording_cap(max_bytes)
                result = self.pool.call("start_recording", session_id=session.id,
                                        path=str(path), snapshot_version=bone.grid.version,
                                        bone_name=session.source.source,
                                        max_bytes=max_bytes)
            except Exception:
                shutil.rmtree(path, ignore_errors=True)  # nothing of it is kept
                raise
            session.recording = {"name": path.name, "path": str(path),
                                 "max_bytes": max_bytes, **result}  # type: ignore[dict-item]
            return session.recording

    def status(self, session: ManagedSession) -> dict | None:
        """The running recording's state (None: the session does not record)."""
        if session.recording is None:
            return None
        status = self.pool.call("recording_status", session_id=session.id)
        return {**session.recording, **(status or {})}  # type: ignore[dict-item]

    def stop(self, session: ManagedSession) -> dict:
        """Stop the session's recording; Conflict if it does not record."""
        with session.lock:
            if session.recording is None:
                raise Conflict(f"session {session.id} is not recording")
            return self.end(session) or {}

    def end(self, session: ManagedSession) -> dict | None:
        """Stop the session's recording if it has one (a bone swap, a delete, the server's
        stop), whatever the loop says; its final state, or None. Call with the session's
        lock held."""
        if session.recording is None:
            return None
        info = session.recording
        session.recording = None
        try:
            status = self.pool.workers[session.worker].call("stop_recording",
                                                            session_id=session.id)
        except RuntimeError as exc:
            status = {"error": str(exc)}
        return {**info, **(status or {})}
