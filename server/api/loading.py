"""Loading bones for sessions: load jobs on a worker thread, and the shared-memory files that
hand each bone to its hot loop.

A bone is read here (a 5-second CT load never runs in the loop's interpreter), on a thread
that runs behind everything else on the machine (:func:`lower_priority`: niceness
``LOAD_NICE``, ``SCHED_BATCH``) and within a memory budget (``serve``'s ``load_budget_bytes``:
the loaders read a slab at a time and refuse from the header a file whose bone would not
fit), checked against
the session's burr, given the session's material changes, and published into shared memory
(``bone.shared``) in this server's run directory; the loop maps it and the name is unlinked at
once, an open descriptor keeping the memory reachable for a restarted loop
(``WorkerPool.rebuild``). Exports read the bone through the same mapping without asking the
loop.

A job never raises: a bone that cannot be loaded fails its job (``Job.error``); a running
session keeps its old bone, a new one is marked failed.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..bone import Bone
from ..bone.engine import check_burr
from ..bone.loaders import BoneFileError, BoneTooLarge
from ..bone.shared import SharedBone, SharedBoneRef, publish
from ..bone.tally import CarveTally
from .errors import ApiError, Conflict, Gone, Invalid, TooLarge
from .generation import next_generation
from .jobs import Job, JobTable
from .recordings import Recordings
from .sessions import ManagedSession, SessionTable
from .settings import default_primary, with_overrides
from .sources import BoneSource, SourceError
from .workers import WorkerPool, sent_of

log = logging.getLogger("burrforce.api")
#: The loading thread's niceness: behind the hot loops and the control plane's own threads.
LOAD_NICE = 10


def lower_priority() -> None:
    """Put the calling thread (Linux: niceness is per thread) at ``LOAD_NICE`` and under
    ``SCHED_BATCH``, so a load's seconds of inflating and converting take the cores only
    when the hot loops leave them. Where it is not permitted, the thread runs as it is."""
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, max(LOAD_NICE, os.getpriority(os.PRIO_PROCESS,
                                                                           tid)))
        os.sched_setscheduler(tid, os.SCHED_BATCH, os.sched_param(0))
    except (AttributeError, OSError):  # not Linux, or a scheduler it may not leave
        pass


class BoneLoads:
    """Runs bone loads one at a time on a worker thread and owns the sessions' shared bones.

    Args:
        sessions: the session table (a session deleted meanwhile does not get its bone).
        jobs: where jobs are kept for status queries.
        pool: the hot loops (the loaded bone is added to, or swapped in, the session's).
        recordings: a recording ends when its session's bone is replaced.
        run_dir: the folder of this server's shared bones.
        data_dir: the data directory (its bone-generation counter).
        memory_budget_bytes: the most memory one load may take (``load_budget_bytes``);
            None: each load's bone's bytes + 512 MiB.
    """

    def __init__(self, sessions: SessionTable, jobs: JobTable, pool: WorkerPool,
                 recordings: Recordings, run_dir: Path, data_dir: Path,
                 memory_budget_bytes: int | None = None) -> None:
        self.sessions = sessions
        self.jobs = jobs
        self.pool = pool
        self.recordings = recordings
        self.run_dir = run_dir
        self.data_dir = data_dir
        self.memory_budget_bytes = memory_budget_bytes
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="burrforce-load",
                                            initializer=lower_priority)
        self._file_counter = 0
        self._counter_lock = threading.Lock()

    def submit(self, session: ManagedSession, kind: str, bone: BoneSource) -> Job:
        """Start loading ``bone`` into ``session`` (``kind``: create, load, reset, restore).
        A running session stays ready (cut, exported) on its old bone until the swap."""
        job = self.jobs.new(kind, session.id, bone.source)
        if not session.in_loop:
            session.state, session.error = "loading", None
        session.job_id = job.id
        self._executor.submit(self._run, session, job, bone)
        return job

    def replace(self, session: ManagedSession, bone: BoneSource, kind: str = "load") -> Job:
        """Replace the session's bone (a new source, a reset or a restore); Conflict while
        it loads one already."""
        with session.lock:
            job = self.jobs.get(session.job_id or "")
            if job is not None and job.active:
                raise Conflict(f"session {session.id} is already loading a bone (job "
                               f"{job.id})")
            return self.submit(session, kind, bone)

    def _run(self, session: ManagedSession, job: Job, source: BoneSource) -> None:
        job.state = "running"

        def progress(stage: str, done: int, total: int) -> None:
            job.stage, job.done, job.total = stage, int(done), int(total)

        try:
            job.stage = "reading"
            bone = source.load(progress, self.memory_budget_bytes)
            job.stage = "checking"
            try:
                check_burr(bone.grid.spacing_mm, session.params, session.shaft)
            except ValueError as exc:
                raise Invalid(str(exc)) from None
            carve, session.pending_carve = session.pending_carve, None
            tally = None
            if carve is not None:
                job.stage = "replaying the journal"
                tally = carve(bone)  # the removal and contacts the journal kept
            job.stage = "sharing"
            ref = self._publish(session, bone, tally)
            del bone
            job.stage = "starting"
            self._install(session, ref, source)
            job.state = "done"
        except ApiError as exc:
            self._fail(session, job, exc.detail, None if isinstance(exc, Invalid) else type(exc))
        except BoneTooLarge as exc:  # answered 413, naming what it needs and the budget
            self._fail(session, job, str(exc), TooLarge)
        except (BoneFileError, SourceError, ValueError, OSError, RuntimeError) as exc:
            self._fail(session, job, str(exc))
        except MemoryError:
            self._fail(session, job, "not enough memory to load the bone")
        except Exception as exc:  # the worker must survive anything a loader throws
            log.exception("loading %s failed", source.source)
            self._fail(session, job, f"{type(exc).__name__}: {exc}")
        finally:
            job.finished_s = time.time()
            job.finished.set()

    def _publish(self, session: ManagedSession, bone: Bone,
                 tally: CarveTally | None = None) -> SharedBoneRef:
        with self._counter_lock:
            self._file_counter += 1
            name = f"session-{session.id}-{self._file_counter}.bone"
        return publish(bone, self.run_dir, name, tally)

    def _install(self, session: ManagedSession, ref: SharedBoneRef,
                 source: BoneSource) -> None:
        """Hand the shared bone ``ref`` to the session's loop and make it the session's."""
        with session.lock:
            if self.sessions.get(session.id) is not session:
                Path(ref.path).unlink(missing_ok=True)
                raise Gone("the session was deleted while its bone loaded")
            self.recordings.end(session)
            reader = SharedBone(ref)
            materials = reader.materials()
            primary = session.primary_label
            if primary is None or primary not in materials:
                primary = default_primary(materials)
            if None in session.overrides and primary is not None:
                overrides = dict(session.overrides)
                overrides[primary] = {**overrides.pop(None), **overrides.get(primary, {})}
                session.overrides = overrides
            try:
                materials = with_overrides(materials, primary, session.overrides)
                spec = self.pool.spec(session, ref, materials)
                info = self.pool.call("replace_session" if session.in_loop
                                      else "add_session", spec=spec)
            except (ApiError, ValueError) as exc:
                reader.close()
                Path(ref.path).unlink(missing_ok=True)
                if isinstance(exc, ValueError):
                    raise Invalid(str(exc)) from None
                raise
            # Both processes map it now: the name can go, so no crash leaves it behind;
            # the descriptor keeps the memory reachable for a restarted loop.
            fd = os.open(ref.path, os.O_RDWR)
            Path(ref.path).unlink(missing_ok=True)
            session.sent = sent_of(spec)
            old = (session.reader, session.ref, session.bone_fd)
            session.in_loop = True
            session.ref, session.reader, session.bone_fd = ref, reader, fd
            session.materials, session.primary_label = materials, primary
            session.source = source
            # After session.reader, never before: generation.py's "Reading order".
            session.bone_info = {**bone_summary(reader, info),  # type: ignore[arg-type]
                                 "generation": next_generation(self.data_dir)}
            session.state, session.error = "ready", None
            close_bone(*old)

    @staticmethod
    def _fail(session: ManagedSession, job: Job, message: str,
              failure: type[ApiError] | None = None) -> None:
        job.state, job.error = "failed", message
        job.failure = failure
        # A session that already runs keeps its bone; a new one is marked failed.
        if session.in_loop:
            session.state, session.error = "ready", None
        else:
            session.state, session.error = "failed", message

    def drop_bone(self, session: ManagedSession) -> None:
        """Unmap and unlink the session's shared bone (it was deleted)."""
        close_bone(session.reader, session.ref, session.bone_fd)
        session.reader = session.ref = session.bone_fd = None

    def close(self) -> None:
        """Stop taking jobs (queued ones are cancelled)."""
        self._executor.shutdown(wait=False, cancel_futures=True)


def close_bone(reader: SharedBone | None, ref: SharedBoneRef | None,
               fd: int | None = None) -> None:
    if reader is not None:
        reader.close()
    if fd is not None:
        os.close(fd)
    if ref is not None:
        # The loop may still map it until its old engine is collected: unlinking only
        # removes the name; the memory goes with the last mapping.
        Path(ref.path).unlink(missing_ok=True)


def bone_summary(reader: SharedBone, info: dict) -> dict:
    """The session view's ``bone``: the shared bone's geometry and the loop's ``voxel_mm``."""
    ref = reader.ref
    lo = np.array(ref.origin_mm)
    return {"name": ref.name, "format": ref.format, "kind": ref.kind,
            "shape": list(ref.shape), "spacing_mm": list(ref.spacing_mm),
            "origin_mm": lo.tolist(), "direction": [list(r) for r in ref.direction],
            "voxel_mm": info.get("voxel_mm"), "notes": list(ref.notes),
            "memory_bytes": ref.size_bytes}

