"""A session report from a recording: the recorded replies, and a replay for what they lack."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ..record import Recording, read_recording, replay
from .model import DEFAULT_THRESHOLD_N, ForbiddenContact, SessionReport, check_threshold


def report_from_recording(
    recording: str | Path | Recording,
    threshold_N: float = DEFAULT_THRESHOLD_N,
    progress: Callable[[int, int], None] | None = None,
) -> SessionReport:
    """Report on a ``.burrrec`` recording.

    Times, status and the hand force are the recorded replies' (what the trainee felt: for a
    coupled session the coupled output's force, which a replay does not recompute). The
    volume removed per material and the forbidden contacts come from replaying the recording
    (the rows hold only the total removed per tick); a note says when the replay does not
    reproduce the recording. Replaying costs about as much CPU time as the session took to
    compute.

    Raises:
        RecordingError: not a recording, or one that cannot be replayed.
        ValueError: a bad threshold.
    """
    check_threshold(threshold_N)
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    replayed = replay(rec, progress=progress)
    rows = rec.rows
    t0 = int(rows["t_recv_ns"][0]) if len(rows) else 0
    t_s = (rows["t_recv_ns"] - t0) * 1e-9
    contacts = [ForbiddenContact.from_event(e["t_s"], e) for e in replayed.forbidden_events]
    notes = [*rec.problems, *replayed.notes]
    if rec.stopped_reason:
        notes.append(f"recording stopped early: {rec.stopped_reason}")
    if not replayed.reproduced:
        notes.append(f"the replay differs from the recording on {replayed.mismatched_ticks} "
                     "ticks (another machine or burrforce version?): the removed volumes and "
                     "forbidden contacts are the replay's, times and forces the recording's")
    session_id = rec.meta.get("session_id")
    started = rec.meta.get("start_time")
    return SessionReport.from_ticks(
        source=rec.path.name,
        source_kind="recording",
        t_s=t_s,
        status=rows["status"],
        hand_force_N=replayed.recorded_force_N,
        removed_mm3_by_material=replayed.removed_mm3_by_material,
        forbidden_contacts=contacts,
        threshold_N=threshold_N,
        session_id=int(session_id) if isinstance(session_id, int) else None,
        started_at=str(started) if started else None,
        complete=rec.complete,
        notes=notes,
    )
