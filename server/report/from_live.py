"""A session report from a live session: its telemetry history and its engine's state."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from datetime import UTC, datetime

import numpy as np

from .model import DEFAULT_THRESHOLD_N, ForbiddenContact, SessionReport, check_threshold


def report_from_live(
    session_id: int,
    t_s: np.ndarray,
    status: np.ndarray,
    hand_force_N: np.ndarray,
    removed_mm3_by_material: Mapping[str, float],
    events: Iterable[Mapping],
    threshold_N: float = DEFAULT_THRESHOLD_N,
    *,
    hz: float,
    installs: np.ndarray | None = None,
    dropped: int = 0,
    wall_offset_s: float | None = None,
    more_notes: Iterable[str] = (),
) -> SessionReport:
    """Report on a live session from its sampled history (``api.history``) and its state
    (``/state``: the engine's removed volume per material and forbidden-contact events).

    Args:
        t_s: sample times on the server's monotonic clock, s, (n,), non-decreasing.
        status: STATUS_* bits per sample, (n,).
        hand_force_N: |force| the hand got per sample, N, (n,).
        removed_mm3_by_material: mm³ per material since the session's bone was loaded.
        events: ``/state``'s ``events``: ``time_s`` (monotonic clock, s), ``label``,
            ``material``, ``position_mm``.
        hz: the history's sampling rate, Hz.
        installs: the install each sample was answered by, (n,).
        dropped: samples older than the history's window.
        wall_offset_s: ``time.time() − time.monotonic()``, for ``started_at``.
        more_notes: notes from elsewhere (the session journal's state).

    Raises:
        ValueError: a bad threshold, or arrays of different lengths.
    """
    check_threshold(threshold_N)
    t_abs = np.asarray(t_s, dtype=np.float64)
    status = np.asarray(status).astype(np.int64)
    n = len(t_abs)
    t0 = float(t_abs[0]) if n else 0.0
    events = list(events)
    first_event = min((float(e["time_s"]) for e in events), default=t0)
    if n and t0 - 2.0 / hz <= first_event < t0:
        # In the stream's first packets, before the first sample: times count from it.
        t0 = first_event
    notes = [f"hand force and cutting time sampled at {hz:g} Hz from live telemetry; a "
             "1 kHz stream's ticks between samples are not seen"]
    if dropped:
        notes.append(f"the history keeps the last {n} samples ({(t_abs[-1] - t0) / 60:.0f} "
                     f"min): {dropped} older ones are not in the times and forces")
    if installs is not None and n:
        changes = np.flatnonzero(np.diff(np.asarray(installs)) != 0) + 1
        if changes.size:
            at = float(t_abs[changes[-1]] - t0)
            notes.append(f"the hot loop restarted or the bone was reloaded at {at:.1f} s "
                         f"({changes.size} time(s)): a restart keeps the removed volumes "
                         "and forbidden contacts, a new bone starts them over")
    contacts = [ForbiddenContact.from_event(float(e["time_s"]) - t0, e) for e in events]
    early = sum(c.time_s < 0.0 for c in contacts)
    if early:
        notes.append(f"{early} forbidden contact(s) precede the history (negative times)")
    notes.extend(more_notes)
    started = None
    if n and wall_offset_s is not None:
        started = datetime.fromtimestamp(t0 + wall_offset_s, UTC).isoformat(
            timespec="seconds")
    return SessionReport.from_ticks(
        source=f"session {session_id}",
        source_kind="session",
        t_s=t_abs - t0,
        status=status,
        hand_force_N=hand_force_N,
        removed_mm3_by_material=removed_mm3_by_material,
        forbidden_contacts=contacts,
        threshold_N=threshold_N,
        session_id=session_id,
        started_at=started,
        complete=dropped == 0,
        notes=notes,
    )
