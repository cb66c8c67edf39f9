"""Bone-load jobs (a new session, a new bone, a reset, a restore), queryable while they run and
for a while after (``JOBS_KEPT``)."""

from __future__ import annotations

import secrets
import threading
import time
from dataclasses import dataclass, field

from .errors import ApiError

#: Jobs kept for status queries after they finish.
JOBS_KEPT = 200


@dataclass
class Job:
    """A bone load, queryable while it runs."""

    id: str
    kind: str
    session_id: int
    source: str
    state: str = "queued"  # queued | running | done | failed
    error: str | None = None
    stage: str = ""
    done: int = 0
    total: int = 0
    created_s: float = field(default_factory=time.time)
    finished_s: float | None = None
    #: What a failed load failed with, when it was not the bone (Unavailable: the hot loop
    #: was restarting, try again; Conflict: the loop has the session id already); None for
    #: a bone that could not be loaded.
    failure: type[ApiError] | None = None
    #: Set when the job is done or failed.
    finished: threading.Event = field(default_factory=threading.Event, repr=False)

    @property
    def active(self) -> bool:
        """Queued or running."""
        return self.state in ("queued", "running")

    def public(self) -> dict:
        return {"id": self.id, "kind": self.kind, "session": self.session_id,
                "source": self.source, "state": self.state, "error": self.error,
                "progress": {"stage": self.stage, "done": self.done, "total": self.total},
                "created": self.created_s, "finished": self.finished_s}

    def wait(self, timeout_s: float = 600.0) -> bool:
        """Wait until the job is done or failed (True) or ``timeout_s`` passes (False)."""
        return self.finished.wait(timeout_s)


class JobTable:
    """Jobs by id, the newest ``JOBS_KEPT`` finished ones kept; thread-safe."""

    def __init__(self, kept: int = JOBS_KEPT) -> None:
        self.kept = kept
        self._by_id: dict[str, Job] = {}
        self._lock = threading.Lock()

    def new(self, kind: str, session_id: int, source: str) -> Job:
        """A queued job, added (the oldest finished ones dropped past ``kept``)."""
        job = Job(secrets.token_hex(8), kind, session_id, source)
        with self._lock:
            self._by_id[job.id] = job
            while len(self._by_id) > self.kept:
                oldest = next(iter(self._by_id))
                if self._by_id[oldest].active:
                    break
                del self._by_id[oldest]
        return job

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            return self._by_id.get(job_id)

    def __getitem__(self, job_id: str) -> Job:
        with self._lock:
            return self._by_id[job_id]

    def values(self) -> list[Job]:
        with self._lock:
            return list(self._by_id.values())

    def loading(self, sources: set[str]) -> list[str]:
        """The ids of the active jobs that read one of ``sources``."""
        return [j.id for j in self.values() if j.active and j.source in sources]
