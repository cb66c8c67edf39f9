"""Reading and writing dynamometer recordings (burrforce.server.calib.recording)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.calib.recording import (
    MIN_SAMPLES,
    Recording,
    RecordingError,
    load_recording,
    save_recording,
)
from burrforce.server.calib.synthetic import synthetic_recording

RATE = 3000.0
N = 100


@pytest.fixture(scope="module")
def force() -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.normal(0.0, 2.0, (N, 3))


def write_csv(path, header: str | None, rows, sep: str = ",", comments=(), fmt=repr) -> None:
    lines = [f"# {c}" for c in comments]
    if header is not None:
        lines.append(header)
    lines += [sep.join(fmt(float(v)) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def with_time(force: np.ndarray, rate: float = RATE) -> np.ndarray:
    return np.column_stack([np.arange(len(force)) / rate, force])


# --- round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip(tmp_path, suffix):
    meta = {"orientation": "parallel", "angle_deg": 30.0, "label": "30", "empty": "",
            "spaced": " x ", "quoted": '"q"', "rpm": 60000.0}
    rec = synthetic_recording((1.0, -2.0, 3.0), noise_N=0.1, drift_N_s=0.05, seed=3,
                              free_s=0.1, burring_s=0.2, metadata=meta)
    path = save_recording(tmp_path / f"rec{suffix}", rec)
    back = load_recording(path)
    assert np.array_equal(back.force_N, rec.force_N)
    assert back.sample_rate_hz == rec.sample_rate_hz
    assert back.metadata == meta
    assert back.source == str(path)
    assert back.duration_s == pytest.approx(0.1 + 0.1 + 0.2 + 0.1 + 0.1)  # free, ramps, burring
    assert not back.force_N.flags.writeable


def test_npz_keeps_metadata_types_csv_reads_numbers_as_float(tmp_path, force):
    rec = Recording(force, RATE, "mem", {"replicate": 2, "ok": True, "name": "a b"})
    npz = load_recording(save_recording(tmp_path / "r.npz", rec))
    assert npz.metadata == {"replicate": 2, "ok": True, "name": "a b"}
    assert type(npz.metadata["replicate"]) is int and type(npz.metadata["ok"]) is bool
    csv = load_recording(save_recording(tmp_path / "r.csv", rec))
    assert csv.metadata == {"replicate": 2.0, "ok": "True", "name": "a b"}
    assert type(csv.metadata["replicate"]) is float


FORCE_SPELLINGS = [("Fx", "Fy", "Fz"), ("fx_N", "fy_N", "fz_N"), ("Fx [N]", "Fy [N]", "Fz [N]"),
                   ("Fx (N)", "Fy (N)", "Fz (N)"), ("FX", "fY", "fz_n"), ('"Fx"', '"Fy"', '"Fz"')]
TIME_SPELLINGS = ["t", "t_s", "time", "time [s]", "time_s", "Time (s)", "T"]


@pytest.mark.parametrize("names", FORCE_SPELLINGS)
def test_header_force_spellings(tmp_path, force, names):
    path = tmp_path / "h.csv"
    # Columns out of order, with an ignored column: matched by name.
    rows = np.column_stack([force[:, 2], np.ones(N), force[:, 0], force[:, 1]])
    write_csv(path, ",".join([names[2], "trigger", names[0], names[1]]), rows)
    rec = load_recording(path, RATE)
    assert np.array_equal(rec.force_N, force)


@pytest.mark.parametrize("name", TIME_SPELLINGS)
def test_header_time_spellings_give_the_rate(tmp_path, force, name):
    path = tmp_path / "t.csv"
    write_csv(path, f"{name},Fx [N],Fy [N],Fz [N]", with_time(force, 2500.0))
    rec = load_recording(path)
    assert rec.sample_rate_hz == pytest.approx(2500.0, rel=1e-12)
    assert np.array_equal(rec.force_N, force)


def test_headerless_three_and_four_columns(tmp_path, force):
    three, four = tmp_path / "3.csv", tmp_path / "4.csv"
    write_csv(three, None, force)
    write_csv(four, None, with_time(force))
    assert np.array_equal(load_recording(three, RATE).force_N, force)
    rec = load_recording(four)
    assert rec.sample_rate_hz == pytest.approx(RATE) and np.array_equal(rec.force_N, force)


@pytest.mark.parametrize("sep", [";", "\t", " ", "  ", ", "])
def test_delimiters(tmp_path, force, sep):
    path = tmp_path / "d.csv"
    write_csv(path, None, with_time(force), sep=sep)
    rec = load_recording(path)
    assert np.array_equal(rec.force_N, force) and rec.sample_rate_hz == pytest.approx(RATE)


def test_semicolon_with_decimal_comma_and_header(tmp_path, force):
    path = tmp_path / "eu.csv"
    write_csv(path, "Zeit [s];Fx [N];Fy [N];Fz [N]".replace("Zeit", "time"),
              with_time(force), sep=";", fmt=lambda v: f"{v:.6f}".replace(".", ","))
    rec = load_recording(path)
    assert np.allclose(rec.force_N, force, atol=1e-6)
    assert rec.sample_rate_hz == pytest.approx(RATE, rel=1e-6)


def test_rounded_timestamps_give_the_exact_rate(tmp_path, force):
    path = tmp_path / "r.csv"
    write_csv(path, "t,fx,fy,fz", with_time(force), fmt=lambda v: f"{v:.6f}")
    # Intervals alternate 0.000333 / 0.000334 s: the span, not the median, gives 3000 Hz.
    assert load_recording(path, RATE).sample_rate_hz == RATE


def test_comment_metadata(tmp_path, force):
    path = tmp_path / "m.csv"
    comments = ["Kistler 9257B, recorded 2024-01-01 12:30", "sample_rate_hz = 3000",
                "orientation: parallel", "angle_deg = 60", "depth_mm=0.5", 'label = "007"']
    write_csv(path, "fx,fy,fz", force, comments=comments)
    rec = load_recording(path)
    assert rec.sample_rate_hz == 3000.0
    assert rec.metadata == {"orientation": "parallel", "angle_deg": 60.0, "depth_mm": 0.5,
                            "label": "007"}


def test_npz_axis_entries_and_time(tmp_path, force):
    path = tmp_path / "a.npz"
    np.savez(path, fx_N=force[:, 0], fy_N=force[:, 1], fz_N=force[:, 2],
             t_s=np.arange(N) / 2000.0, operator=np.bytes_(b"ab"), trace=np.zeros(5),
             angle_deg=np.float32(30.0))
    rec = load_recording(path)
    assert np.array_equal(rec.force_N, force)
    assert rec.sample_rate_hz == pytest.approx(2000.0)
    assert rec.metadata == {"operator": "ab", "angle_deg": 30.0}  # arrays are not metadata


# --- the rate --------------------------------------------------------------------------------


def test_rate_precedence(tmp_path, force):
    path = tmp_path / "p.csv"
    write_csv(path, None, force, comments=["sample_rate_hz = 3000"])
    assert load_recording(path).sample_rate_hz == 3000.0
    assert load_recording(path, 3002.0).sample_rate_hz == 3002.0  # within 0.1 %: the argument
    with pytest.raises(RecordingError, match=r"passed, 3100 Hz, differs .*3000 Hz"):
        load_recording(path, 3100.0)
    bare = tmp_path / "bare.csv"
    write_csv(bare, None, force)
    assert load_recording(bare, 1234.0).sample_rate_hz == 1234.0
    with pytest.raises(RecordingError, match=r"no sample rate in the file.*pass one"):
        load_recording(bare)


@pytest.mark.parametrize("rate", [0.0, -3000.0, math.nan, math.inf])
def test_rate_must_be_positive_and_finite(tmp_path, force, rate):
    path = tmp_path / "p.csv"
    write_csv(path, None, force)
    with pytest.raises(RecordingError, match=r"finite and > 0"):
        load_recording(path, rate)


def test_rate_conflict_inside_the_file(tmp_path, force):
    path = tmp_path / "c.csv"
    write_csv(path, "t,fx,fy,fz", with_time(force, 2000.0), comments=["sample_rate_hz = 3000"])
    with pytest.raises(RecordingError, match=r"3000 Hz.*time column.*2000 Hz"):
        load_recording(path)
    npz = tmp_path / "c.npz"
    np.savez(npz, force_N=force, sample_rate_hz=3000.0, t_s=np.arange(N) / 2000.0)
    with pytest.raises(RecordingError, match=r"3000 Hz.*t_s.*2000 Hz"):
        load_recording(npz)


# --- CSV errors ------------------------------------------------------------------------------


def test_non_numeric_cell_names_line_and_column(tmp_path, force):
    path = tmp_path / "bad.csv"
    write_csv(path, "t,fx,fy,fz", with_time(force), comments=["note"])
    lines = path.read_text().splitlines()
    lines[6] = lines[6].split(",")[0] + ",oops,1,2"
    path.write_text("\n".join(lines))
    with pytest.raises(RecordingError, match=r"bad\.csv: line 7, column 2 \(fx\): 'oops'"):
        load_recording(path)


def test_nan_and_inf_are_counted(tmp_path, force):
    path = tmp_path / "nan.csv"
    bad = force.copy()
    bad[10, 1], bad[20, 2] = np.nan, np.inf
    write_csv(path, "fx,fy,fz", bad)
    with pytest.raises(RecordingError, match=r"2 NaN or infinite value\(s\); the first on line "
                                             r"12, column 2 \(fy\)"):
        load_recording(path, RATE)


def test_too_few_samples(tmp_path, force):
    path = tmp_path / "short.csv"
    write_csv(path, None, force[: MIN_SAMPLES - 1])
    with pytest.raises(RecordingError, match=rf"{MIN_SAMPLES - 1} data rows; at least "
                                             rf"{MIN_SAMPLES}"):
        load_recording(path, RATE)


def test_time_not_increasing(tmp_path, force):
    rows = with_time(force)
    rows[40, 0] = rows[39, 0]
    path = tmp_path / "t.csv"
    write_csv(path, "t,fx,fy,fz", rows)
    with pytest.raises(RecordingError, match=r"time does not increase at line 42"):
        load_recording(path)


def test_non_uniform_sampling(tmp_path, force):
    rows = with_time(force)
    rows[50:, 0] += 0.1 / RATE  # one interval 10 % long
    path = tmp_path / "t.csv"
    write_csv(path, "t,fx,fy,fz", rows)
    with pytest.raises(RecordingError, match=r"non-uniform sampling at line 52"):
        load_recording(path)


@pytest.mark.parametrize(("header", "message"), [
    ("fx,fy,force_z", r"line 1: the header .* no column for fz"),
    ("time,fx,Fx [N],fy,fz", r"columns 2 and 3 are both 'fx'"),
])
def test_bad_headers(tmp_path, force, header, message):
    path = tmp_path / "h.csv"
    width = header.count(",") + 1
    write_csv(path, header, np.column_stack([force] + [force[:, 0]] * (width - 3)))
    with pytest.raises(RecordingError, match=message):
        load_recording(path, RATE)


def test_headerless_needs_three_or_four_columns(tmp_path, force):
    path = tmp_path / "5.csv"
    write_csv(path, None, np.column_stack([force, force[:, :2]]))
    with pytest.raises(RecordingError, match=r"5 comma-separated columns and no header.*3 "
                                             r"\(fx, fy, fz\) or 4"):
        load_recording(path, RATE)


def test_ragged_row(tmp_path, force):
    path = tmp_path / "r.csv"
    write_csv(path, "fx,fy,fz", force)
    lines = path.read_text().splitlines()
    lines[8] = "1,2"
    path.write_text("\n".join(lines))
    with pytest.raises(RecordingError, match=r"line 9: 2 columns, but the header \(line 1\) "
                                             r"has 3"):
        load_recording(path, RATE)


@pytest.mark.parametrize(("content", "message"), [
    (b"", r"no data rows"),
    (b"# sample_rate_hz = 3000\n\n", r"no data rows"),
    (b"1 2\n3 4\n", r"could not find 3 or more columns"),
    (b"fx,fy,fz\n\xff\xfe1,2,3\n", r"line 2: not UTF-8"),
    (b"# sample_rate_hz = fast\n1,2,3\n", r"line 1: sample_rate_hz 'fast' is not a number"),
])
def test_malformed_text(tmp_path, content, message):
    path = tmp_path / "x.csv"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message):
        load_recording(path)


def test_missing_file(tmp_path):
    with pytest.raises(RecordingError, match=r"nope\.csv: no such file"):
        load_recording(tmp_path / "nope.csv")


# --- NPZ errors ------------------------------------------------------------------------------


@pytest.mark.parametrize(("arrays", "message"), [
    ({"forces": np.zeros((N, 3))}, r"no force: expected entry 'force_N'.*found \['forces'\]"),
    ({"force_N": np.zeros((N, 2))}, r"'force_N' must have shape \(n, 3\), got \(100, 2\)"),
    ({"force_N": np.array([["a"] * 3] * N)}, r"entry 'force_N' is not numeric"),
    ({"fx_N": np.zeros(N), "fy_N": np.zeros(N), "fz_N": np.zeros(N - 1)}, r"'fz_N' has shape"),
    ({"force_N": np.zeros((N, 3)), "t_s": np.arange(N - 1.0)}, r"'t_s' must have shape"),
    ({"force_N": np.zeros((N, 3)), "t_s": np.r_[0.0, 1.0, np.arange(3.0, N + 1)]},
     r"entry 't_s': non-uniform sampling at index 2"),
    ({"force_N": np.zeros((N, 3)), "sample_rate_hz": np.array([1.0, 2.0])},
     r"'sample_rate_hz' must be a scalar"),
    ({"force_N": np.full((N, 3), np.nan), "sample_rate_hz": 1.0},
     r"300 non-finite force value\(s\) \(NaN or inf\), the first in sample 0"),
    ({"force_N": np.zeros((10, 3)), "sample_rate_hz": 1.0}, r"10 samples; at least 64"),
    ({"force_N": np.zeros((N, 3)), "sample_rate_hz": -1.0}, r"finite and > 0"),
    ({"force_N": np.zeros((N, 3)), "sample_rate_hz": 1.0, "extra": np.array([None, 1])},
     r"entry 'extra' cannot be read"),
])
def test_npz_errors(tmp_path, arrays, message):
    path = tmp_path / "bad.npz"
    np.savez(path, **arrays)
    with pytest.raises(RecordingError, match=message):
        load_recording(path)


@pytest.mark.parametrize(("content", "message"), [
    (b"not a zip", r"not an NPZ archive"),
    (b"", r"not an NPZ archive"),
])
def test_npz_not_an_archive(tmp_path, content, message):
    path = tmp_path / "x.npz"
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=message):
        load_recording(path)


def test_npy_is_not_npz(tmp_path):
    path = tmp_path / "x.npz"
    with path.open("wb") as handle:
        np.save(handle, np.zeros((N, 3)))
    with pytest.raises(RecordingError, match=r"single \.npy array"):
        load_recording(path)


# --- saving and the Recording itself ---------------------------------------------------------


@pytest.mark.parametrize(("name", "meta", "message"), [
    ("r.xlsx", {}, r"suffix '\.xlsx'"),
    ("r.csv", {"bad key": 1.0}, r"metadata key 'bad key'"),
    ("r.npz", {"force_N": 1.0}, r"'force_N' is reserved"),
    ("r.csv", {"sample_rate_hz": 1.0}, r"'sample_rate_hz' is reserved"),
    ("r.npz", {"trace": [1.0, 2.0]}, r"'trace' must be a scalar"),
    ("r.csv", {"note": "two\nlines"}, r"'note' holds a line break"),
])
def test_save_refuses(tmp_path, force, name, meta, message):
    with pytest.raises(RecordingError, match=message):
        save_recording(tmp_path / name, Recording(force, RATE, "mem", meta))
    assert not any(tmp_path.iterdir())  # nothing half-written


@pytest.mark.parametrize(("force_N", "rate", "message"), [
    (np.zeros((N, 2)), RATE, r"shape \(n, 3\), got \(100, 2\)"),
    (np.zeros((10, 3)), RATE, r"10 samples; at least 64"),
    (np.full((N, 3), np.inf), RATE, r"300 non-finite"),
    (np.zeros((N, 3)), 0.0, r"finite and > 0"),
    ([["a", "b", "c"]] * N, RATE, r"not numeric"),
])
def test_recording_validates(force_N, rate, message):
    with pytest.raises(RecordingError, match=message):
        Recording(force_N, rate, "mem")


# --- fuzz: nothing but RecordingError --------------------------------------------------------


@pytest.fixture(scope="module")
def fuzz_path(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz") / "f.csv"


def _load_or_recording_error(path, rate):
    try:
        rec = load_recording(path, rate)
    except RecordingError:
        return
    assert rec.force_N.shape[1] == 3 and np.isfinite(rec.force_N).all()
    assert rec.sample_rate_hz > 0.0


FUZZ = settings(max_examples=examples(150),
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@FUZZ
@given(data=st.binary(max_size=2000), rate=st.sampled_from([None, RATE]))
def test_fuzz_bytes(fuzz_path, data, rate):
    fuzz_path.write_bytes(data)
    _load_or_recording_error(fuzz_path, rate)


CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**30, 10**30).map(str),
    st.sampled_from(["", "fx", "Fy [N]", "fz_N", "t", "time [s]", "nan", "1,5", '"2"', "#",
                     "# sample_rate_hz = 3000", "sample_rate_hz: -1", "1e999", "0x10", "1_0"]),
    st.text(max_size=6),
)
ROWS = st.lists(st.lists(CELLS, min_size=0, max_size=5), max_size=8)


@FUZZ
@given(head=ROWS, sep=st.sampled_from([",", ";", "\t", " "]), body=st.integers(0, 80),
       width=st.integers(3, 4), tail=ROWS, rate=st.sampled_from([None, RATE]),
       end=st.sampled_from(["\n", "\r\n", "\r"]))
def test_fuzz_text(fuzz_path, head, sep, body, width, tail, rate, end):
    # Junk around a plausible numeric body, so the fuzz reaches the deep checks too.
    rows = [sep.join(r) for r in head]
    rows += [sep.join(str(i / RATE) if (width == 4 and j == 0) else f"{(i * j) % 7 - 3}.5"
                      for j in range(width)) for i in range(body)]
    rows += [sep.join(r) for r in tail]
    fuzz_path.write_text(end.join(rows), encoding="utf-8", errors="surrogatepass")
    _load_or_recording_error(fuzz_path, rate)


@FUZZ
@given(text=st.text(max_size=500))
def test_fuzz_unicode(fuzz_path, text):
    fuzz_path.write_bytes(text.encode("utf-8", errors="surrogatepass"))
    _load_or_recording_error(fuzz_path, None)


def test_units_in_the_header_are_applied_never_ignored(tmp_path):
    rows = "\n".join(f"{i / 3:.6f},{0.001 * i},0.002,-0.003" for i in range(100))
    path = tmp_path / "kn.csv"
    path.write_text("time [ms],Fx [kN],fy_mN,Fz (N)\n" + rows + "\n")
    rec = load_recording(path)
    assert rec.sample_rate_hz == pytest.approx(3000.0, rel=1e-4)
    assert rec.force_N[10].tolist() == pytest.approx([10.0, 2e-6, -0.003])
    (tmp_path / "lbf.csv").write_text("t,Fx [lbf],Fy,Fz\n" + rows + "\n")
    with pytest.raises(RecordingError, match="unknown force unit 'lbf'"):
        load_recording(tmp_path / "lbf.csv")
    (tmp_path / "min.csv").write_text("Time (min),Fx,Fy,Fz\n" + rows + "\n")
    with pytest.raises(RecordingError, match="unknown time unit 'min'"):
        load_recording(tmp_path / "min.csv")


def test_saved_recordings_are_readable_by_others_as_the_umask_allows(tmp_path):
    import os
    import stat

    old = os.umask(0o022)
    try:
        for name in ("a.csv", "a.npz"):
            path = save_recording(tmp_path / name, synthetic_recording([0, 0, -1], seed=0))
            assert stat.S_IMODE(path.stat().st_mode) == 0o644
    finally:
        os.umask(old)
