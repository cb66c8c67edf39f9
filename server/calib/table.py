"""The case table: one row per replicate, the case's geometry and its mean force components.

Plain form: a CSV with the columns ``orientation`` (parallel | perpendicular | diagonal, the
geometry of model.md), ``angle_deg``, ``depth_mm``, ``feed_mm_s``, ``rpm``, ``radius_mm``,
``feed_N``, ``lateral_N``, ``normal_N``; an optional ``source`` column names where the row came
from (a recording). Forces are the bone's force on the burr, resolved as model.md says: feed
along the feed direction, normal along the outward surface normal, lateral along ŝ × f̂.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model.cases import ORIENTATIONS, CuttingCase

GEOMETRY_COLUMNS = ("orientation", "angle_deg", "depth_mm", "feed_mm_s", "rpm", "radius_mm")
FORCE_COLUMNS = ("feed_N", "lateral_N", "normal_N")
COLUMNS = GEOMETRY_COLUMNS + FORCE_COLUMNS
COMPONENTS = ("feed", "lateral", "normal")
#: A mean cutting force beyond this is not a burr's (the model's own inputs stop far below).
MAX_FORCE_N = 1e4


class CaseTableError(ValueError):
    """A case table that cannot be used; the message names the file, line and column."""


@dataclass(frozen=True)
class CaseRow:
    """One replicate: a cutting case and the mean force components measured in it, N."""

    case: CuttingCase
    feed_N: float
    lateral_N: float
    normal_N: float
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        for name in FORCE_COLUMNS:  # numpy scalars would leak into CSV and JSON as such
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def forces_N(self) -> np.ndarray:
        """(3,) feed, lateral, normal, N."""
        return np.array([self.feed_N, self.lateral_N, self.normal_N])

    def as_dict(self) -> dict[str, object]:
        c = self.case
        row: dict[str, object] = {
            "orientation": c.orientation, "angle_deg": c.angle_deg, "depth_mm": c.depth_mm,
            "feed_mm_s": c.feed_mm_s, "rpm": c.rpm, "radius_mm": c.radius_mm,
            "feed_N": self.feed_N, "lateral_N": self.lateral_N, "normal_N": self.normal_N,
        }
        if self.source:
            row["source"] = self.source
        return row


def case_key(case: CuttingCase) -> tuple:
    """Cases with equal keys are replicates of one another."""
    return (case.orientation, case.angle_deg, case.depth_mm, case.feed_mm_s, case.rpm,
            case.radius_mm)


def row_from_mapping(values: dict[str, object], where: str) -> CaseRow:
    """A :class:`CaseRow` from a mapping of column → value (strings or numbers).

    Raises:
        CaseTableError: a missing or bad value, named with ``where`` (e.g. "cases.csv line 4").
    """
    missing = [c for c in COLUMNS if values.get(c) in (None, "")]
    if missing:
        raise CaseTableError(f"{where}: missing {', '.join(missing)}")
    orientation = check_orientation(values["orientation"], where)
    numbers = {c: parse_number(values[c], c, where) for c in COLUMNS[1:]}
    for c in FORCE_COLUMNS:
        if abs(numbers[c]) > MAX_FORCE_N:
            raise CaseTableError(f"{where}: {c} = {numbers[c]:g} N is beyond ±{MAX_FORCE_N:g} N")
    for c in ("feed_mm_s", "rpm", "radius_mm"):
        if numbers[c] <= 0.0:
            raise CaseTableError(f"{where}: {c} must be > 0, got {numbers[c]:g}")
    try:
        case = CuttingCase(orientation, numbers["angle_deg"], radius_mm=numbers["radius_mm"],
                           depth_mm=numbers["depth_mm"], feed_mm_s=numbers["feed_mm_s"],
                           rpm=numbers["rpm"])
    except ValueError as exc:
        raise CaseTableError(f"{where}: {exc}") from None
    return CaseRow(case, numbers["feed_N"], numbers["lateral_N"], numbers["normal_N"],
                   str(values.get("source") or ""))


def check_orientation(value: object, where: str) -> str:
    """The orientation's name, case-folded; CaseTableError naming ``where`` if unknown."""
    orientation = str(value).strip().lower()
    if orientation not in ORIENTATIONS:
        raise CaseTableError(f"{where}: orientation must be one of "
                             f"{', '.join(ORIENTATIONS)}, got {value!r}")
    return orientation


def parse_number(value: object, column: str, where: str) -> float:
    """A finite float from a cell (a decimal comma accepted); CaseTableError naming ``where``
    and ``column`` otherwise."""
    text = value.strip() if isinstance(value, str) else value
    if isinstance(text, str) and "," in text and "." not in text:
        text = text.replace(",", ".")  # a decimal comma (the file is ;- or tab-separated)
    try:
        number = float(text)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise CaseTableError(f"{where}: {column} is not a number: {value!r}") from None
    if not math.isfinite(number):
        raise CaseTableError(f"{where}: {column} must be finite, got {value!r}")
    return number


def read_case_table(path: str | Path) -> list[CaseRow]:
    """Read a case table CSV (comma, semicolon or tab separated; ``#`` lines are comments).

    Raises:
        CaseTableError: the file cannot be read, a column is missing, or a row is bad (the
            message names the line and column). Nothing is skipped silently.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaseTableError(f"cannot read the case table {path}: {exc}") from None
    return parse_case_table(text, str(path))


def parse_case_table(text: str, name: str = "case table") -> list[CaseRow]:
    """:func:`read_case_table` on text already in memory."""
    numbered = [(i, line) for i, line in enumerate(text.splitlines(), start=1)
                if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise CaseTableError(f"{name}: no header and no rows")
    header_line = numbered[0][1]
    delimiter = max((",", ";", "\t"), key=header_line.count)
    reader = csv.reader(io.StringIO("\n".join(line for _, line in numbered)),
                        delimiter=delimiter)
    canonical = {c.lower(): c for c in (*COLUMNS, "source")}
    header = [canonical.get(h.strip().lower(), h.strip()) for h in next(reader)]
    absent = [c for c in COLUMNS if c not in header]
    if absent:
        raise CaseTableError(
            f"{name} line {numbered[0][0]}: the header lacks {', '.join(absent)} (a case table "
            f"has the columns {', '.join(COLUMNS)}; got {', '.join(header)})")
    duplicated = sorted({h for h in header if header.count(h) > 1 and h in COLUMNS})
    if duplicated:
        raise CaseTableError(f"{name}: column {', '.join(duplicated)} appears twice")
    rows = []
    for (line_no, _), cells in zip(numbered[1:], reader, strict=True):
        where = f"{name} line {line_no}"
        if len(cells) != len(header):
            raise CaseTableError(f"{where}: {len(cells)} cells, the header has {len(header)}")
        rows.append(row_from_mapping(dict(zip(header, (c.strip() for c in cells),
                                              strict=True)), where))
    if not rows:
        raise CaseTableError(f"{name}: a header but no rows")
    return rows


def write_case_table(path: str | Path, rows: Iterable[CaseRow]) -> Path:
    """Write rows as a case table CSV (with a ``source`` column when any row has one)."""
    path = Path(path)
    rows = list(rows)
    columns = list(COLUMNS) + (["source"] if any(r.source for r in rows) else [])
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore",
                                lineterminator="\n")
        writer.writeheader()
        for r in rows:
            writer.writerow({k: _format(v) for k, v in r.as_dict().items()})
    return path


def _format(value: object) -> object:
    return repr(float(value)) if isinstance(value, (float, np.floating)) else value


def group_rows(rows: Sequence[CaseRow]) -> dict[tuple, list[CaseRow]]:
    """Replicates grouped by case, in first-seen order."""
    groups: dict[tuple, list[CaseRow]] = {}
    for r in rows:
        groups.setdefault(case_key(r.case), []).append(r)
    return groups
