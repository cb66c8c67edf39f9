"""How a session's journal stands, as its view, ``/v1/health`` and ``/metrics`` show it: written,
degraded (it cannot be written: the next restart would lose what was cut since) or off, and
what a restart lost when its journal was damaged (``journal_resume``)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class JournalStatus:
    """One session's journal (the journal thread updates it; readers copy ``view()``).

    Attributes:
        state: ``off`` (no journal: an embedded server, or before its first pass),
            ``ok`` (the last pass wrote everything) or ``degraded`` (it could not).
        written_s: when a pass last wrote everything, Unix time, s.
        failing_since_s: when the passes began to fail (None while they succeed).
        error: why the last pass failed.
        recovery: what this session's resume from a damaged or incomplete journal lost
            (``journal_resume.Recovery.as_dict``), None when it lost nothing.
    """

    state: str = "off"
    written_s: float | None = None
    failing_since_s: float | None = None
    error: str | None = None
    recovery: dict | None = None

    def written(self, now_s: float) -> None:
        self.state, self.written_s = "ok", now_s
        self.failing_since_s = self.error = None

    def failed(self, error: str, now_s: float) -> None:
        if self.failing_since_s is None:
            self.failing_since_s = now_s
        self.state, self.error = "degraded", error

    def view(self) -> dict:
        """The session view's ``journal``."""
        return {"state": self.state, "written": self.written_s,
                "failing_since": self.failing_since_s, "error": self.error,
                "recovery": self.recovery}

    def notes(self) -> list[str]:
        """Lines for the session's report: a journal that cannot be written, a loss at the
        last restart."""
        out = []
        if self.state == "degraded":
            out.append(f"the session journal cannot be written ({self.error}): a restart "
                       "now would lose the carving since it failed")
        if self.recovery is not None:
            out.append(f"resumed from a damaged or incomplete journal: "
                       f"{self.recovery['summary']}")
        return out
