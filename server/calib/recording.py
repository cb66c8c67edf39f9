"""Dynamometer recordings: a 3-axis force signal sampled at a fixed rate, read from CSV or NPZ.

The thesis (§2.4) records the x, y and z forces of a Kistler dynamometer at 3 kHz. A
:class:`Recording` holds those three channels, the sample rate, where they came from, and the
file's extra scalar fields (case fields such as ``orientation`` or ``angle_deg``).

CSV (any suffix but ``.npz``)
    Delimiter sniffed among comma, semicolon, tab and whitespace (with a semicolon, tab or
    whitespace delimiter a decimal comma is accepted). Comment lines before the data,
    ``# key = value`` or ``# key: value`` (key: letters, digits, ``_ . -``), become metadata;
    values are numbers (float) where they parse, else strings (``"..."`` keeps a string that
    looks like a number a string). ``# sample_rate_hz = 3000`` gives the rate. The header row
    is optional: with one, columns are matched case-insensitively after dropping a unit in
    brackets or parentheses and a trailing ``_n`` (forces: ``fx fy fz``; time: ``t`` or
    ``time``, optionally ``_s``); other columns are ignored. Without one, 3 columns are
    fx, fy, fz and 4 are t, fx, fy, fz. A time column gives the rate.
NPZ
    ``force_N`` (n, 3), or ``fx_N``, ``fy_N``, ``fz_N`` (n,) each; ``sample_rate_hz`` (scalar)
    and/or ``t_s`` (n,); every other 0-d entry is metadata.

Every problem raises :class:`RecordingError` naming the file and, where there is one, the line
and column (CSV) or entry (NPZ).
"""

from __future__ import annotations

import math
import os
import re
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..whole_files import WholeFile

#: Fewer samples than this cannot hold a free-spinning and a burring region.
MIN_SAMPLES = 64
#: A rate in the file and one passed in may differ by this fraction before they conflict.
RATE_TOLERANCE = 1e-3
#: Sampling intervals may vary by this fraction of their mean (timestamps are rounded).
DT_TOLERANCE = 0.01

_FORCE_KEYS = ("fx_N", "fy_N", "fz_N")
_RESERVED_KEYS = frozenset({"force_N", "sample_rate_hz", "t_s", *_FORCE_KEYS})
_META_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_.\-]*")
_META_LINE = re.compile(r"\s*(?P<key>[A-Za-z_][A-Za-z0-9_.\-]*)\s*[=:]\s*(?P<value>.*?)\s*")
_UNIT = re.compile(r"\[[^\]]*\]|\([^)]*\)")
_DELIMITERS = ("\t", ";", ",", None)  # None: runs of whitespace; earlier wins a tie
_DELIMITER_NAMES = {"\t": "tab", ";": "semicolon", ",": "comma", None: "whitespace"}
_SNIFF_ROWS = 50


class RecordingError(ValueError):
    """A recording that cannot be read or written; the message names the file and the place."""


@dataclass(frozen=True, eq=False)
class Recording:
    """A 3-axis force recording.

    Attributes:
        force_N: (n, 3) float64, read-only: the dynamometer's x, y, z channels, N.
        sample_rate_hz: samples per second, finite and > 0.
        source: the file it came from, or a description.
        metadata: extra scalar fields found in the file (never arrays).
    """

    force_N: np.ndarray
    sample_rate_hz: float
    source: str = "<memory>"
    metadata: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        try:
            force = np.array(self.force_N, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"{self.source}: force_N is not numeric ({exc})") from None
        if force.ndim != 2 or force.shape[1] != 3:
            raise RecordingError(
                f"{self.source}: force_N must have shape (n, 3), got {force.shape}")
        if force.shape[0] < MIN_SAMPLES:
            raise RecordingError(f"{self.source}: {force.shape[0]} samples; at least "
                                 f"{MIN_SAMPLES} are needed")
        bad = ~np.isfinite(force)
        if bad.any():
            row = int(np.argmax(bad.any(axis=1)))
            raise RecordingError(f"{self.source}: {int(bad.sum())} non-finite force value(s) "
                                 f"(NaN or inf), the first in sample {row}")
        rate = _check_rate(self.sample_rate_hz, str(self.source))
        force.flags.writeable = False
        object.__setattr__(self, "force_N", force)
        object.__setattr__(self, "sample_rate_hz", rate)
        object.__setattr__(self, "source", str(self.source))
        object.__setattr__(self, "metadata", dict(self.metadata))

    @property
    def n_samples(self) -> int:
        return int(self.force_N.shape[0])

    @property
    def duration_s(self) -> float:
        """n / sample_rate_hz: each sample stands for one sampling interval."""
        return self.n_samples / self.sample_rate_hz

    @property
    def t_s(self) -> np.ndarray:
        """(n,) the sample times, s, from 0."""
        return np.arange(self.n_samples) / self.sample_rate_hz


def _check_rate(rate: object, where: str) -> float:
    try:
        value = float(rate)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise RecordingError(f"{where}: sample rate {rate!r} is not a number") from None
    if not math.isfinite(value) or value <= 0.0:
        raise RecordingError(f"{where}: sample rate must be finite and > 0 Hz, got {value}")
    return value


def _resolve_rate(where: str, passed: float | None, in_file: float | None,
                  file_what: str) -> float:
    if passed is not None:
        passed = _check_rate(passed, where)
    if in_file is not None:
        in_file = _check_rate(in_file, where)
    if passed is None and in_file is None:
        raise RecordingError(f"{where}: no sample rate in the file (no '# sample_rate_hz = …' "
                             "line, time column or sample_rate_hz entry); pass one "
                             "(sample_rate_hz=…)")
    if passed is not None and in_file is not None:
        if abs(passed - in_file) > RATE_TOLERANCE * max(passed, in_file):
            raise RecordingError(f"{where}: the sample rate passed, {passed:g} Hz, differs from "
                                 f"the file's ({file_what}), {in_file:g} Hz")
        return passed
    return passed if passed is not None else in_file  # type: ignore[return-value]


def _rate_from_times(t_s: np.ndarray, where: str, place: Callable[[int], str]) -> float:
    """1 / the mean interval of uniformly increasing times; ``place(i)`` names sample i.

    Every interval must lie within 1 % of the median one. The rate is from the mean interval
    (span / (n − 1)), not the median: timestamps rounded to a few digits alternate between
    two intervals, and the span averages that rounding away.
    """
    with np.errstate(all="ignore"):
        dt = np.diff(t_s)
        bad = ~(dt > 0.0) | ~np.isfinite(dt)
        if bad.any():
            i = int(np.argmax(bad)) + 1
            raise RecordingError(f"{where}: time does not increase at {place(i)} "
                                 f"({t_s[i]!r} after {t_s[i - 1]!r})")
        mean_dt = float((t_s[-1] - t_s[0]) / (len(t_s) - 1))
        typical = float(np.median(dt))  # one odd interval must not shift the reference
        off = np.abs(dt - typical) > DT_TOLERANCE * typical
    if off.any():
        i = int(np.argmax(off)) + 1
        raise RecordingError(
            f"{where}: non-uniform sampling at {place(i)}: interval {dt[i - 1]:.6g} s vs "
            f"the typical {typical:.6g} s (more than {DT_TOLERANCE:.0%} apart); resample it")
    rate = 1.0 / mean_dt if mean_dt > 0.0 else math.inf
    if not math.isfinite(rate) or rate <= 0.0:
        raise RecordingError(f"{where}: the time column gives no usable sample rate")
    return rate


# --- CSV -------------------------------------------------------------------------------------


def _split(line: str, delimiter: str | None) -> list[str]:
    if delimiter is None:
        return line.split()
    cells = [c.strip() for c in line.split(delimiter)]
    while cells and cells[-1] == "":  # a trailing delimiter is not a column
        cells.pop()
    return cells


def _unquote(text: str) -> str:
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "\"'":
        return text[1:-1]
    return text


def _number(cell: str, decimal_comma: bool) -> float | None:
    cell = _unquote(cell.strip())
    try:
        return float(cell)
    except ValueError:
        pass
    if decimal_comma and cell.count(",") == 1 and "." not in cell:
        try:
            return float(cell.replace(",", "."))
        except ValueError:
            return None
    return None


def _meta_value(text: str) -> object:
    if len(text) >= 2 and text[0] == text[-1] == '"':
        return text[1:-1]
    try:
        return float(text)
    except ValueError:
        return text


def _sniff(rows: list[str], where: str) -> str | None:
    """The delimiter splitting the first rows into the most consistent ≥ 3 columns."""
    best, best_score = None, -1.0
    for delimiter in _DELIMITERS:
        counts = [len(_split(r, delimiter)) for r in rows]
        mode = max(set(counts), key=lambda c: (counts.count(c), c))
        if mode < 3:
            continue
        score = counts.count(mode) / len(counts)
        if score > best_score:
            best, best_score = delimiter, score
    if best_score < 0.0:
        raise RecordingError(f"{where}: could not find 3 or more columns separated by a comma, "
                             "semicolon, tab or whitespace in the first data rows")
    return best


_FORCE_UNITS = {"n": 1.0, "kn": 1e3, "mn": 1e-3}
_TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}


def _canonical(name: str, where: str) -> tuple[str, float] | None:
    """'Fx [N]', 'fx_N', 'Fx (kN)' → ('fx', 1 or 1000); 'time [ms]', 't_s', 'Time' → ('t',
    seconds per unit); else None. A force or time column in a unit other than N/kN/mN or
    s/ms/µs is an error, never read as newtons or seconds."""
    text = _unquote(name.strip())
    units = [u.strip().lower() for u in re.findall(r"\[([^\]]*)\]|\(([^)]*)\)", text)
             for u in u if u]
    base = _UNIT.sub("", text).strip().lower().rstrip("_ ")
    stem, _, suffix = base.rpartition("_")
    if stem and not units and (suffix in _FORCE_UNITS or suffix in _TIME_UNITS):
        base, units = stem, [suffix]
    if base in ("fx", "fy", "fz"):
        canon, table, kind = base, _FORCE_UNITS, "force"
    elif base in ("t", "time"):
        canon, table, kind = "t", _TIME_UNITS, "time"
    else:
        return None
    if not units:
        return canon, 1.0
    unit = units[-1]
    if unit not in table:
        raise RecordingError(f"{where}: column {name.strip()!r}: unknown {kind} unit {unit!r} "
                             f"(known: {', '.join(table)})")
    return canon, table[unit]


def _read_csv(path: Path, sample_rate_hz: float | None) -> Recording:
    where = str(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise RecordingError(f"{where}: cannot read: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise RecordingError(f"{where}: line {line}: not UTF-8 text (byte {exc.start}); is "
                             "this a CSV file?") from None
    lines = re.split(r"\r\n|\r|\n", text)

    metadata: dict[str, object] = {}
    rate_in_file: float | None = None
    data: list[tuple[int, str]] = []  # (1-based line number, text)
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            if data:
                continue  # comments after the data starts are notes, not metadata
            match = _META_LINE.fullmatch(stripped[1:])
            if match is None:
                continue  # free text
            key, value = match["key"], _meta_value(match["value"])
            if key == "sample_rate_hz":
                if not isinstance(value, float):
                    raise RecordingError(f"{where}: line {number}: sample_rate_hz {value!r} "
                                         "is not a number")
                rate_in_file = _check_rate(value, f"{where}: line {number}")
            else:
                metadata[key] = value
            continue
        data.append((number, line))
    if not data:
        raise RecordingError(f"{where}: no data rows")

    delimiter = _sniff([row for _, row in data[:_SNIFF_ROWS]], where)
    decimal_comma = delimiter != ","
    first_line, first = data[0]
    cells = _split(first, delimiter)
    unit_scale: dict[str, float] = {}
    numeric = sum(_number(c, decimal_comma) is not None for c in cells)
    if numeric * 2 < len(cells):  # mostly words: a header
        parsed = [_canonical(c, f"{where}: line {first_line}") for c in cells]
        columns: dict[str, int] = {}
        for i, entry in enumerate(parsed):
            if entry is None:
                continue
            name, unit_scale[name] = entry
            if name in columns:
                raise RecordingError(f"{where}: line {first_line}: columns {columns[name] + 1} "
                                     f"and {i + 1} are both {name!r}")
            columns[name] = i
        missing = [a for a in ("fx", "fy", "fz") if a not in columns]
        if missing:
            raise RecordingError(
                f"{where}: line {first_line}: the header {cells!r} has no column for "
                f"{', '.join(missing)} (accepted e.g. Fx, fx_N, 'Fx [N]', 'Fx (N)')")
        header = cells
        data = data[1:]
    else:
        header = None
        if len(cells) == 3:
            columns = {"fx": 0, "fy": 1, "fz": 2}
        elif len(cells) == 4:
            columns = {"t": 0, "fx": 1, "fy": 2, "fz": 3}
        else:
            raise RecordingError(
                f"{where}: line {first_line}: {len(cells)} {_DELIMITER_NAMES[delimiter]}-"
                "separated columns and no header; without a header there must be 3 (fx, fy, "
                "fz) or 4 (t, fx, fy, fz); add a header row naming the columns")
    width = len(header) if header is not None else len(cells)

    wanted = [(k, columns[k]) for k in ("t", "fx", "fy", "fz") if k in columns]
    values = np.empty((len(data), len(wanted)), dtype=np.float64)
    line_numbers = np.empty(len(data), dtype=np.int64)
    for r, (number, line) in enumerate(data):
        row = _split(line, delimiter)
        if len(row) != width:
            what = f"the header (line {first_line}) has" if header else "the first row has"
            raise RecordingError(f"{where}: line {number}: {len(row)} columns, but {what} "
                                 f"{width}")
        for c, (name, index) in enumerate(wanted):
            value = _number(row[index], decimal_comma)
            if value is None:
                raise RecordingError(f"{where}: line {number}, column {index + 1} ({name}): "
                                     f"{row[index]!r} is not a number")
            values[r, c] = value
        line_numbers[r] = number

    def place(i: int) -> str:
        return f"line {line_numbers[i]}"

    bad = ~np.isfinite(values)
    if bad.any():
        r = int(np.argmax(bad.any(axis=1)))
        c = int(np.argmax(bad[r]))
        name, index = wanted[c]
        raise RecordingError(f"{where}: {int(bad.sum())} NaN or infinite value(s); the first on "
                             f"line {line_numbers[r]}, column {index + 1} ({name})")
    if len(values) < MIN_SAMPLES:
        raise RecordingError(f"{where}: {len(values)} data rows; at least {MIN_SAMPLES} are "
                             "needed")
    for c, (name, _) in enumerate(wanted):  # to N and s
        values[:, c] *= unit_scale.get(name, 1.0)
    file_what = "its '# sample_rate_hz' line"
    if "t" in columns:
        from_times = _rate_from_times(values[:, 0], where, place)
        if rate_in_file is not None:
            _resolve_rate(where, rate_in_file, from_times, "its time column")
        else:
            rate_in_file, file_what = from_times, "from its time column"
    rate = _resolve_rate(where, sample_rate_hz, rate_in_file, file_what)
    return Recording(values[:, -3:], rate, where, metadata)


# --- NPZ -------------------------------------------------------------------------------------


def _scalar(value: np.ndarray) -> object:
    item = value.item()
    if isinstance(item, bytes):
        return item.decode("utf-8", errors="replace")
    if isinstance(item, (bool, int, float, str)):
        return item
    return str(item)


def _read_npz(path: Path, sample_rate_hz: float | None) -> Recording:
    where = str(path)
    try:
        archive = np.load(path, allow_pickle=False)
    except OSError as exc:
        raise RecordingError(f"{where}: cannot read: {exc.strerror or exc}") from None
    except (ValueError, EOFError, zipfile.BadZipFile):
        raise RecordingError(f"{where}: not an NPZ archive") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise RecordingError(f"{where}: a single .npy array, not an NPZ archive of named "
                             "entries (force_N, sample_rate_hz, …)")
    with archive:
        entries: dict[str, np.ndarray] = {}
        for key in archive.files:
            try:
                value = archive[key]
            except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
                raise RecordingError(f"{where}: entry {key!r} cannot be read ({exc})") from None
            if isinstance(value, np.ndarray):  # a zip may hold members that are not arrays
                entries[key] = value

    def numeric(key: str) -> np.ndarray:
        value = entries[key]
        if value.dtype.kind not in "iuf":
            raise RecordingError(f"{where}: entry {key!r} is not numeric ({value.dtype})")
        return value.astype(np.float64)

    if "force_N" in entries:
        force = numeric("force_N")
        if force.ndim != 2 or force.shape[1] != 3:
            raise RecordingError(f"{where}: entry 'force_N' must have shape (n, 3), got "
                                 f"{force.shape}")
    elif all(k in entries for k in _FORCE_KEYS):
        axes = [numeric(k) for k in _FORCE_KEYS]
        for key, axis in zip(_FORCE_KEYS, axes, strict=True):
            if axis.ndim != 1 or axis.shape != axes[0].shape:
                raise RecordingError(f"{where}: entries fx_N, fy_N, fz_N must be 1-D of one "
                                     f"length; {key!r} has shape {axis.shape}")
        force = np.stack(axes, axis=1)
    else:
        raise RecordingError(f"{where}: no force: expected entry 'force_N' (n, 3) or entries "
                             f"'fx_N', 'fy_N', 'fz_N'; found {sorted(entries)}")
    # Recording() checks the values themselves (finite, enough samples).
    rate_in_file: float | None = None
    file_what = "entry sample_rate_hz"
    if "sample_rate_hz" in entries:
        value = numeric("sample_rate_hz")
        if value.size != 1:
            raise RecordingError(f"{where}: entry 'sample_rate_hz' must be a scalar, got shape "
                                 f"{value.shape}")
        rate_in_file = _check_rate(value.reshape(()).item(), f"{where}: entry 'sample_rate_hz'")
    if "t_s" in entries:
        t_s = numeric("t_s")
        if t_s.shape != (len(force),):
            raise RecordingError(f"{where}: entry 't_s' must have shape ({len(force)},), got "
                                 f"{t_s.shape}")
        from_times = _rate_from_times(t_s, f"{where}: entry 't_s'", lambda i: f"index {i}")
        if rate_in_file is not None:
            _resolve_rate(where, rate_in_file, from_times, "entry t_s")
        else:
            rate_in_file, file_what = from_times, "from entry t_s"
    rate = _resolve_rate(where, sample_rate_hz, rate_in_file, file_what)
    metadata = {k: _scalar(v) for k, v in entries.items()
                if k not in _RESERVED_KEYS and v.ndim == 0}
    return Recording(force, rate, where, metadata)


# --- public ----------------------------------------------------------------------------------


def load_recording(path: str | Path, sample_rate_hz: float | None = None) -> Recording:
    """Read a recording (``.npz`` by suffix, anything else as CSV text; see the module doc).

    ``sample_rate_hz``, if given, is the rate; a rate the file also gives must agree within
    0.1 %. Without it the file must give one.

    Raises:
        RecordingError: the file is missing, unreadable or malformed (the message names the
            line and column, or the entry), the rate is missing or conflicting, there are
            NaN/inf values or fewer than :data:`MIN_SAMPLES` samples.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    if path.suffix.lower() == ".npz":
        return _read_npz(path, sample_rate_hz)
    return _read_csv(path, sample_rate_hz)


def _checked_metadata(metadata: Mapping[str, object], where: str) -> dict[str, object]:
    out: dict[str, object] = {}
    for key, value in metadata.items():
        if not isinstance(key, str) or not _META_KEY.fullmatch(key):
            raise RecordingError(f"{where}: metadata key {key!r} must be letters, digits, "
                                 "'_', '.', '-' and start with a letter or '_'")
        if key in _RESERVED_KEYS:
            raise RecordingError(f"{where}: metadata key {key!r} is reserved")
        if isinstance(value, np.generic):
            value = value.item()
        if isinstance(value, bytes):
            value = value.decode("utf-8", errors="replace")
        if not isinstance(value, (str, bool, int, float)):
            raise RecordingError(f"{where}: metadata {key!r} must be a scalar (str, number, "
                                 f"bool), got {type(value).__name__}")
        if isinstance(value, str) and ("\n" in value or "\r" in value):
            raise RecordingError(f"{where}: metadata {key!r} holds a line break")
        out[key] = value
    return out


def _csv_value(value: object) -> str:
    if isinstance(value, str):
        plain = value == value.strip() and not (value[:1] == '"' == value[-1:])
        try:
            float(value)
        except ValueError:
            if plain:
                return value
        return f'"{value}"'  # quoted, it reads back as this string
    if isinstance(value, bool):
        return f'"{value}"'
    return repr(float(value)) if isinstance(value, float) else str(value)


def _write_atomic(path: Path, write: Callable[[object], object]) -> None:
    # A recording is data to share: the umask decides its mode, not mkstemp's 0600.
    umask = os.umask(0)
    os.umask(umask)
    with WholeFile(path, permissions=0o666 & ~umask) as handle:
        write(handle)


def save_recording(path: str | Path, recording: Recording) -> Path:
    """Write ``recording`` as ``.csv`` or ``.npz`` (by suffix) so that :func:`load_recording`
    reads back the same forces, rate and metadata. Returns the path.

    CSV: ``# sample_rate_hz = …`` and ``# key = value`` lines, an ``fx_N,fy_N,fz_N`` header,
    floats written to round-trip exactly. Integer and boolean metadata read back from CSV as a
    float and the string ``"True"``/``"False"``; NPZ keeps their types.

    Raises:
        RecordingError: another suffix, or metadata that is not a scalar under a plain key.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    metadata = _checked_metadata(recording.metadata, str(path))
    if suffix == ".npz":
        arrays = {"force_N": np.asarray(recording.force_N, dtype=np.float64),
                  "sample_rate_hz": np.float64(recording.sample_rate_hz),
                  **{k: np.asarray(v) for k, v in metadata.items()}}
        _write_atomic(path, lambda handle: np.savez_compressed(handle, **arrays))
    elif suffix in (".csv", ".txt", ".tsv"):
        lines = [f"# sample_rate_hz = {recording.sample_rate_hz!r}"]
        lines += [f"# {k} = {_csv_value(v)}" for k, v in metadata.items()]
        lines.append(",".join(_FORCE_KEYS))
        lines += [",".join(map(repr, row)) for row in recording.force_N.tolist()]
        body = ("\n".join(lines) + "\n").encode("utf-8")
        _write_atomic(path, lambda handle: handle.write(body))
    else:
        raise RecordingError(f"{path}: cannot tell the format from suffix {path.suffix!r}; use "
                             ".csv or .npz")
    return path
