"""What a session report holds: :class:`SessionReport`, built from per-tick arrays."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ...proto.messages import STATUS_CONTACT, STATUS_CUTTING, STATUS_SHAFT_CONTACT
from .series import MAX_SERIES_POINTS, downsample_min_max, runs, tick_durations_s

#: The default force threshold, N. Above every steady |F| of the thesis's nine cases at the
#: demo's 5 mm/s feed (largest 1.78 N, parallel at 60°: ``burrforce experiment --feed-mm-s 5``),
#: so time above it is time pushing harder or faster than a controlled 0.5 mm cut; and below
#: the smallest device peak, the Touch's 3.3 N (``haptics/profiles.py``), where the coupled
#: output clamps, so the time still shows on every device.
DEFAULT_THRESHOLD_N = 2.0
#: The largest threshold taken, N: far above any hand force (devices render ~10 N), and the
#: report's plot scales its axis to it (1.8e308 N overflowed the axis ticks: a 500).
MAX_THRESHOLD_N = 1e4
#: Status bits of a tick in contact: the burr or its shaft in bone.
CONTACT_STATUS = STATUS_CUTTING | STATUS_CONTACT | STATUS_SHAFT_CONTACT
SOURCE_KINDS = ("recording", "session")
#: Cutting runs closer than this share of the duration are drawn as one.
MERGE_SHARE = 1e-3


@dataclass(frozen=True)
class ForbiddenContact:
    """Contact with a forbidden structure began. ``time_s`` from the report's first tick;
    ``position_mm`` the touched point in the bone's world frame (the server's frame), mm."""

    time_s: float
    label: int
    material: str
    position_mm: tuple[float, float, float]

    @classmethod
    def from_event(cls, time_s: float, event: Mapping[str, Any]) -> ForbiddenContact:
        """From an engine's forbidden-contact event (``label``, ``material``, ``position_mm``;
        a replay's or ``/state``'s), at ``time_s`` on the report's clock."""
        x, y, z = (float(v) for v in event["position_mm"])
        return cls(float(time_s), int(event["label"]), str(event["material"]), (x, y, z))

    def to_dict(self) -> dict[str, Any]:
        return {"time_s": _num(self.time_s), "label": self.label, "material": self.material,
                "position_mm": [_num(x) for x in self.position_mm]}


@dataclass
class SessionReport:
    """A session's report for an instructor: how long, how much cut, what was touched, how
    hard the hand pushed.

    Where each field comes from. For a recording (``from_recording``): the recorded rows and
    a replay of them (``record.replay``). For a live session (``from_live``):
    ``removed_mm3_by_material`` and ``forbidden_contacts`` from the session engine's state
    (``/state``'s ``removed_mm3`` and ``events``, their ``time_s`` on the server's monotonic
    clock less the first sample's); the per-tick time, status and hand force from the
    control plane's 100 Hz telemetry history (``api.history``), so ``ticks`` counts samples,
    not packets; ``started_at`` from the first sample. ``notes`` say so, and what the
    bounded history left out.

    Attributes:
        source: the recording's directory name, or ``session N``.
        source_kind: ``recording`` or ``session``.
        session_id: the session that was recorded, if known.
        started_at: wall-clock start (ISO 8601), if known.
        ticks: ticks the report covers.
        duration_s: from the first tick to the last, s.
        cutting_s: time with the burr removing bone (``STATUS_CUTTING``), s; each tick counts
            until the next (``series.tick_durations_s``: a silence longer than
            ``series.MAX_TICK_S`` is a gap in the stream and counts one typical tick).
        contact_s: time with the burr or shaft in bone (``CONTACT_STATUS``), s; counted alike.
        removed_mm3: bone removed, all materials, mm³.
        removed_mm3_by_material: mm³ per material name.
        forbidden_contacts: contacts with forbidden structures, in time order.
        hand_force_peak_N: the largest |force| the replies carried (what the hand was sent:
            the coupled output's force when the session had one), N, over every tick.
        hand_force_mean_N: the mean |force| over the ticks in contact (``CONTACT_STATUS``),
            each tick weighing the same, N; 0 without contact.
        threshold_N: the force threshold, N.
        time_above_threshold_s: time with |force| > ``threshold_N``, s (counted as
            ``cutting_s``).
        series_t_s, series_force_N: |force| over time for the plot, at most
            ``MAX_SERIES_POINTS`` points keeping every bin's minimum and maximum; float64.
        cutting_intervals_s: [start_s, end_s] stretches of cutting, for shading the plot.
        complete: the source covers the whole session (a recording closed by its recorder,
            nothing torn).
        notes: what a reader should know about the numbers.
    """

    source: str
    source_kind: str
    session_id: int | None
    started_at: str | None
    ticks: int
    duration_s: float
    cutting_s: float
    contact_s: float
    removed_mm3: float
    removed_mm3_by_material: dict[str, float]
    forbidden_contacts: list[ForbiddenContact]
    hand_force_peak_N: float
    hand_force_mean_N: float
    threshold_N: float
    time_above_threshold_s: float
    series_t_s: np.ndarray = field(repr=False)
    series_force_N: np.ndarray = field(repr=False)
    cutting_intervals_s: list[tuple[float, float]] = field(repr=False)
    complete: bool = True
    notes: list[str] = field(default_factory=list)

    @classmethod
    def from_ticks(
        cls,
        *,
        source: str,
        source_kind: str,
        t_s: np.ndarray,
        status: np.ndarray,
        hand_force_N: np.ndarray,
        removed_mm3_by_material: Mapping[str, float],
        forbidden_contacts: Iterable[ForbiddenContact],
        threshold_N: float = DEFAULT_THRESHOLD_N,
        session_id: int | None = None,
        started_at: str | None = None,
        complete: bool = True,
        notes: Iterable[str] = (),
        max_points: int = MAX_SERIES_POINTS,
    ) -> SessionReport:
        """A report from per-tick arrays.

        Args:
            t_s: tick times from the first tick, s, shape (n,), non-decreasing.
            status: the replies' ``STATUS_*`` bits, integer (n,).
            hand_force_N: |force| the replies carried, N, (n,).
            removed_mm3_by_material: mm³ per material name.
            forbidden_contacts: times from the first tick.
            threshold_N: a finite force > 0.

        Raises:
            ValueError: a bad threshold or source kind, or arrays of different lengths.
        """
        check_threshold(threshold_N)
        if source_kind not in SOURCE_KINDS:
            raise ValueError(f"source_kind must be one of {SOURCE_KINDS}, got {source_kind!r}")
        t_s = np.asarray(t_s, dtype=np.float64)
        status = np.asarray(status).astype(np.int64)
        force = np.asarray(hand_force_N, dtype=np.float64)
        n = len(t_s)
        if len(status) != n or len(force) != n:
            raise ValueError(f"t_s, status and hand_force_N differ in length: {n}, "
                             f"{len(status)}, {len(force)}")
        dt = tick_durations_s(t_s)
        cutting = (status & STATUS_CUTTING) != 0
        contact = (status & CONTACT_STATUS) != 0
        duration = float(t_s[-1] - t_s[0]) if n else 0.0
        by_material = {str(k): float(v) for k, v in removed_mm3_by_material.items()}
        series_t, series_f = downsample_min_max(t_s, force, max_points)
        return cls(
            source=source,
            source_kind=source_kind,
            session_id=session_id,
            started_at=started_at,
            ticks=n,
            duration_s=duration,
            cutting_s=float(dt[cutting].sum()),
            contact_s=float(dt[contact].sum()),
            removed_mm3=float(sum(by_material.values())),
            removed_mm3_by_material=by_material,
            forbidden_contacts=sorted(forbidden_contacts, key=lambda c: c.time_s),
            hand_force_peak_N=float(force.max()) if n else 0.0,
            hand_force_mean_N=float(force[contact].mean()) if contact.any() else 0.0,
            threshold_N=float(threshold_N),
            time_above_threshold_s=float(dt[force > threshold_N].sum()),
            series_t_s=series_t,
            series_force_N=series_f,
            cutting_intervals_s=runs(t_s, cutting, dt, MERGE_SHARE * duration),
            complete=complete,
            notes=list(notes),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: non-finite numbers become null."""
        return {
            "source": self.source,
            "source_kind": self.source_kind,
            "session_id": self.session_id,
            "started_at": self.started_at,
            "ticks": self.ticks,
            "duration_s": _num(self.duration_s),
            "cutting_s": _num(self.cutting_s),
            "contact_s": _num(self.contact_s),
            "removed_mm3": _num(self.removed_mm3),
            "removed_mm3_by_material": {k: _num(v) for k, v in
                                        self.removed_mm3_by_material.items()},
            "forbidden_contacts": [c.to_dict() for c in self.forbidden_contacts],
            "hand_force_peak_N": _num(self.hand_force_peak_N),
            "hand_force_mean_N": _num(self.hand_force_mean_N),
            "threshold_N": _num(self.threshold_N),
            "time_above_threshold_s": _num(self.time_above_threshold_s),
            "series": {"t_s": [_num(x) for x in self.series_t_s.tolist()],
                       "force_N": [_num(x) for x in self.series_force_N.tolist()]},
            "cutting_intervals_s": [[_num(a), _num(b)] for a, b in self.cutting_intervals_s],
            "complete": self.complete,
            "notes": list(self.notes),
        }

    def format_text(self) -> str:
        """A short summary for a terminal."""
        removed = ", ".join(f"{name} {v:.4g}" for name, v in
                            self.removed_mm3_by_material.items()) or "none"
        lines = [
            f"{self.source}" + (f" (started {self.started_at})" if self.started_at else ""),
            f"  {self.duration_s:.2f} s, cutting {self.cutting_s:.2f} s, in contact "
            f"{self.contact_s:.2f} s ({self.ticks} ticks)",
            f"  removed {self.removed_mm3:.4g} mm³ ({removed})",
            f"  hand force: peak {self.hand_force_peak_N:.3g} N, mean in contact "
            f"{self.hand_force_mean_N:.3g} N; above {self.threshold_N:g} N for "
            f"{self.time_above_threshold_s:.2f} s",
            f"  forbidden contacts: {len(self.forbidden_contacts)}",
        ]
        for c in self.forbidden_contacts[:10]:
            x, y, z = c.position_mm
            lines.append(f"    t = {c.time_s:.3f} s: {c.material} (label {c.label}) at "
                         f"({x:.2f}, {y:.2f}, {z:.2f}) mm")
        if len(self.forbidden_contacts) > 10:
            lines.append(f"    … {len(self.forbidden_contacts) - 10} more")
        lines.extend(f"  note: {n}" for n in self.notes)
        return "\n".join(lines)


def check_threshold(threshold_N: float) -> float:
    """``threshold_N`` if it is a number in (0, MAX_THRESHOLD_N] N; else ValueError."""
    if isinstance(threshold_N, bool) or not isinstance(threshold_N, (int, float)) \
            or not 0.0 < threshold_N <= MAX_THRESHOLD_N:  # also refuses NaN
        raise ValueError(f"the force threshold must be a number in (0, {MAX_THRESHOLD_N:g}] "
                         f"N, got {threshold_N!r}")
    return float(threshold_N)


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
