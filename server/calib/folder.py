"""A folder of dynamometer recordings → a case table, a report per recording, and the drill's
vibration parameters.

Each recording is one replicate of one case. Its case (orientation, angle_deg, depth_mm,
feed_mm_s, rpm, radius_mm) comes from a ``manifest.csv`` in the folder (a ``file`` column plus
those columns) or, for any column the manifest lacks, from the recording's own metadata (NPZ
scalars, ``# key = value`` lines of a CSV). Optional columns:

- ``sample_rate_hz``: when the file does not carry it.
- ``forces_on``: ``workpiece`` (default: a dynamometer under the bone measures the burr's force
  on the bone) or ``burr``. The table holds the force on the burr (model.md), so ``workpiece``
  readings are negated.
- ``feed_axis``, ``normal_axis``: the feed direction and the outward bone-surface normal in the
  dynamometer's frame, as ``x``, ``-y``, ``+z`` or three numbers (``0.7071 0.7071 0``). Default:
  the dynamometer's frame is the case's (model.md), so the feed is the orientation's direction
  and the normal is +z.

Components then follow model.md: feed = F·f̂, normal = F·ŝ, lateral = F·(ŝ × f̂).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from ..model.cases import ORIENTATIONS
from .recording import load_recording
from .signal import RecordingAnalysis, analyse
from .table import (
    GEOMETRY_COLUMNS,
    CaseRow,
    CaseTableError,
    check_orientation,
    parse_number,
    row_from_mapping,
)

MANIFEST = "manifest.csv"
RECORDING_SUFFIXES = (".csv", ".npz")
FORCES_ON = ("workpiece", "burr")
_AXES = {"x": 0, "y": 1, "z": 2}


class FolderError(ValueError):
    """Recordings that cannot be turned into a table; the message lists every file's problem."""


@dataclass(frozen=True)
class RecordingReport:
    """One recording's processing: its table row and what the signal analysis found."""

    row: CaseRow
    analysis: RecordingAnalysis
    forces_on: str
    components_sem_N: np.ndarray          # (3,) standard errors of feed, lateral, normal
    sample_rate_hz: float

    def as_dict(self) -> dict:
        a = self.analysis
        s = a.segments
        fs = self.sample_rate_hz
        return {
            **self.row.as_dict(),
            "feed_sem_N": float(self.components_sem_N[0]),
            "lateral_sem_N": float(self.components_sem_N[1]),
            "normal_sem_N": float(self.components_sem_N[2]),
            "forces_on": self.forces_on,
            "burring_s": [s.burring_full[0] / fs, s.burring_full[1] / fs],
            "analysed_s": [s.burring[0] / fs, s.burring[1] / fs],
            "drift_N_s": s.baseline_N[1].tolist(),
            "vibration_burring_N": a.burring.resultant_fit_N,
            "vibration_burring_peaks_N": a.burring.resultant_peaks_N,
            "vibration_free_N": a.non_burring.resultant_fit_N,
            "vibration_free_peaks_N": a.non_burring.resultant_peaks_N,
            "ratio_fit": a.ratio_fit,
            "ratio_peaks": a.ratio_peaks,
            "dominant_frequency_hz": a.dominant_frequency_hz,
            "spindle_fit_hz": a.burring.frequency_hz,
        }


@dataclass
class FolderResult:
    reports: list[RecordingReport]
    failures: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def rows(self) -> list[CaseRow]:
        return [r.row for r in self.reports]

    def vibration(self, confidence: float = 0.95) -> dict:
        """The drill's vibration parameters (model.md: A = √(Fd² + (g·|F_r|)²)).

        ``fd_N``: the mean free-spinning resultant amplitude (sinusoid fit) with its t interval;
        ``g``: least squares of A_burring² − Fd² = g²·|F_r|² over the recordings, ≥ 0 (the
        thesis found the ratio ≈ 1, i.e. g ≈ 0).
        """
        free = np.array([r.analysis.non_burring.resultant_fit_N for r in self.reports])
        burring = np.array([r.analysis.burring.resultant_fit_N for r in self.reports])
        force = np.array([np.linalg.norm(r.row.forces_N) for r in self.reports])
        n = len(free)
        if n == 0:
            return {}
        fd = float(free.mean())
        if n > 1:
            half = float(stats.t.ppf(0.5 + confidence / 2.0, n - 1) * free.std(ddof=1)
                         / math.sqrt(n))
            fd_ci: list[float] | None = [fd - half, fd + half]
        else:
            fd_ci = None
        denom = float(np.sum(force ** 4))
        g2 = float(np.sum((burring ** 2 - fd ** 2) * force ** 2) / denom) if denom > 0 else 0.0
        return {
            "fd_N": fd, "fd_ci": fd_ci, "g": math.sqrt(max(g2, 0.0)),
            "ratio_fit_mean": float(np.mean([r.analysis.ratio_fit for r in self.reports])),
            "ratio_peaks_mean": float(np.mean([r.analysis.ratio_peaks for r in self.reports])),
            "frequency_hz_mean": float(np.mean(
                [r.analysis.dominant_frequency_hz for r in self.reports])),
            "recordings": n,
        }


def parse_axis(text: str, what: str) -> np.ndarray:
    """A unit vector from ``x``, ``-y``, ``+z`` or three numbers."""
    t = text.strip().lower()
    sign = -1.0 if t.startswith("-") else 1.0
    name = t.lstrip("+-")
    if name in _AXES:
        v = np.zeros(3)
        v[_AXES[name]] = sign
        return v
    try:
        v = np.array([float(p) for p in t.replace(",", " ").split()])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.isfinite(v).all() or np.linalg.norm(v) == 0.0:
        raise ValueError(f"{what} must be x, y, z with an optional sign, or three numbers, "
                         f"got {text!r}")
    return v / np.linalg.norm(v)


def component_basis(feed_axis: np.ndarray, normal_axis: np.ndarray) -> np.ndarray:
    """(3, 3) rows f̂, ŝ × f̂, ŝ. Raises ValueError unless the feed lies in the surface."""
    f = feed_axis / np.linalg.norm(feed_axis)
    s = normal_axis / np.linalg.norm(normal_axis)
    if abs(float(f @ s)) > 1e-3:
        raise ValueError(f"the feed axis {f.round(4).tolist()} is not perpendicular to the "
                         f"surface normal {s.round(4).tolist()}")
    return np.array([f, np.cross(s, f), s])


def read_manifest(path: Path) -> dict[str, dict[str, str]]:
    """file name → its manifest row (values as text)."""
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise FolderError(f"cannot read the manifest {path}: {exc}") from None
    lines = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    if not lines:
        raise FolderError(f"{path}: empty manifest")
    delimiter = max((",", ";", "\t"), key=lines[0].count)
    reader = csv.reader(lines, delimiter=delimiter)
    fields = [f.strip().lower() for f in next(reader)]
    if "file" not in fields:
        raise FolderError(f"{path}: the manifest needs a 'file' column (got "
                          f"{', '.join(fields) or 'none'})")
    out: dict[str, dict[str, str]] = {}
    for i, cells in enumerate(reader, start=2):
        if len(cells) != len(fields):
            raise FolderError(f"{path} row {i}: {len(cells)} cells, the header has "
                              f"{len(fields)}")
        row = dict(zip(fields, (c.strip() for c in cells), strict=True))
        name = row["file"]
        if not name:
            raise FolderError(f"{path} row {i}: no file name")
        if name in out:
            raise FolderError(f"{path} row {i}: {name} is listed twice")
        out[name] = row
    return out


def process_recording(path: Path, fields: dict[str, object],
                      default_forces_on: str = "workpiece",
                      trim_fraction: float = 0.1) -> RecordingReport:
    """One recording → its report. ``fields`` are the manifest's values for it (may be empty).

    Raises:
        ValueError: (RecordingError, CaseTableError, …) naming what is wrong.
    """
    rate = fields.get("sample_rate_hz")
    rate_hz = None if rate in (None, "") else parse_number(rate, "sample_rate_hz", path.name)
    rec = load_recording(path, rate_hz)
    values: dict[str, object] = {k: rec.metadata.get(k) for k in (
        *GEOMETRY_COLUMNS, "forces_on", "feed_axis", "normal_axis")}
    values.update({k: v for k, v in fields.items() if v not in (None, "")})
    missing = [c for c in GEOMETRY_COLUMNS if values.get(c) in (None, "")]
    if missing:
        raise CaseTableError(f"{path.name}: no {', '.join(missing)} in the manifest or the file")
    orientation = check_orientation(values["orientation"], path.name)
    forces_on = str(values.get("forces_on") or default_forces_on).strip().lower()
    if forces_on not in FORCES_ON:
        raise ValueError(f"{path.name}: forces_on must be workpiece or burr, got {forces_on!r}")
    feed_axis = (parse_axis(str(values["feed_axis"]), "feed_axis") if values.get("feed_axis")
                 else np.array(ORIENTATIONS[orientation]))
    normal_axis = (parse_axis(str(values["normal_axis"]), "normal_axis")
                   if values.get("normal_axis") else np.array([0.0, 0.0, 1.0]))
    basis = component_basis(feed_axis, normal_axis)
    rpm = parse_number(values["rpm"], "rpm", path.name)
    analysis = analyse(rec, rpm, trim_fraction=trim_fraction)
    sign = -1.0 if forces_on == "workpiece" else 1.0
    components = basis @ (sign * analysis.mean_force_N)
    sem = np.sqrt((basis ** 2) @ (analysis.mean_force_sem_N ** 2))
    row = row_from_mapping({**values, "orientation": orientation, "feed_N": components[0],
                            "lateral_N": components[1], "normal_N": components[2],
                            "source": path.name}, path.name)
    return RecordingReport(row=row, analysis=analysis, forces_on=forces_on,
                           components_sem_N=sem, sample_rate_hz=rec.sample_rate_hz)


def recording_files(folder: Path, manifest: dict[str, dict[str, str]] | None) -> list[Path]:
    if manifest is not None:
        return [folder / name for name in manifest]
    return sorted(p for p in folder.iterdir()
                  if p.suffix.lower() in RECORDING_SUFFIXES and p.name != MANIFEST
                  and p.is_file())


def process_folder(folder: str | Path, *, manifest: str | Path | None = None,
                   forces_on: str = "workpiece", trim_fraction: float = 0.1,
                   skip_bad: bool = False,
                   progress: Callable[[int, int, str], None] | None = None) -> FolderResult:
    """Process every recording the manifest lists (or every .csv/.npz when there is none).

    Raises:
        FolderError: no recordings, or any recording failed (all failures listed) unless
            ``skip_bad``, in which case they are returned in ``failures`` and at least one
            recording must succeed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FolderError(f"{folder} is not a folder")
    if forces_on not in FORCES_ON:
        raise FolderError(f"forces_on must be workpiece or burr, got {forces_on!r}")
    manifest_path = Path(manifest) if manifest is not None else folder / MANIFEST
    entries = read_manifest(manifest_path) if manifest_path.exists() else None
    if manifest is not None and entries is None:
        raise FolderError(f"no manifest at {manifest_path}")
    files = recording_files(folder, entries)
    if not files:
        raise FolderError(f"{folder} holds no .csv or .npz recordings")
    result = FolderResult(reports=[])
    for i, path in enumerate(files):
        if progress is not None:
            progress(i, len(files), path.name)
        fields: dict[str, object] = dict(entries[path.name]) if entries is not None else {}
        fields.pop("file", None)
        try:
            report = process_recording(path, fields, forces_on, trim_fraction)
            result.reports.append(report)
            spindle = report.row.case.rpm / 60.0
            found = report.analysis.dominant_frequency_hz
            if not abs(found - spindle) <= 0.05 * spindle:
                result.warnings.append(
                    f"{path.name}: the dominant frequency is {found:.4g} Hz, not the spindle's "
                    f"{spindle:.4g} Hz: its vibration amplitudes and ratio are not the drill's "
                    "(no tone above the noise, or a wrong rpm)")
        except (ValueError, OSError) as exc:
            message = str(exc)
            result.failures.append(message if path.name in message else f"{path.name}: {message}")
    if result.failures and (not skip_bad or not result.reports):
        raise FolderError(f"{len(result.failures)} of {len(files)} recording(s) failed:\n  "
                          + "\n  ".join(result.failures))
    return result
