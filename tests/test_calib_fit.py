"""Calibration fitting: the model's linearity in Us and Us·K, recovery of known truth, honest
intervals, cross-validation, the case table's format and its errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.server.calib.design import ModelSetup, Sensitivities
from burrforce.server.calib.fit import FitError, FitOptions, calibrate, fieller, fit_rows
from burrforce.server.calib.table import (
    COLUMNS,
    CaseRow,
    CaseTableError,
    parse_case_table,
    read_case_table,
    write_case_table,
)
from burrforce.server.model import CuttingModel, CuttingParams, thesis_cases

US, K = 805.1, 1.3


@pytest.fixture(scope="module")
def sens():
    return Sensitivities()


@pytest.fixture(scope="module")
def cases():
    return list(thesis_cases())


def _rows(sens, cases, us=US, k=K, replicates=5, noise_N=0.0, seed=0):
    rng = np.random.default_rng(seed)
    model = sens.predict(cases, us, k)
    return [CaseRow(c, *(m + noise_N * rng.standard_normal(3)).tolist())
            for c, m in zip(cases, model, strict=True) for _ in range(replicates)]


# -- the design: every component is Us·(a + K·b) ------------------------------------------------
@settings(max_examples=examples(25), deadline=None)
@given(us=st.floats(1.0, 1e5), k=st.floats(0.0, 5.0), i=st.integers(0, 8))
def test_the_model_is_linear_in_us_and_us_k(sens, cases, us, k, i):
    case = cases[i]
    model = CuttingModel(CuttingParams(us_n_mm2=us, k=k), n_theta=sens.n_theta)
    r = model.evaluate(case.centre_mm, case.axis, case.feed_velocity_mm_s, case.rpm)
    predicted = sens.predict([case], us, k)[0]
    direct = np.array([r.feed_N, r.lateral_N, r.normal_N])
    assert np.allclose(predicted, direct, rtol=1e-9, atol=1e-12 * us)


def test_below_the_cutting_speed_a_case_cannot_inform_us(sens, cases):
    from dataclasses import replace

    with pytest.raises(ValueError, match="below the minimum cutting speed"):
        sens.of(replace(cases[0], rpm=1000.0))


def test_reverse_spin_mirrors_parallel_cutting(cases):
    """Parallel feed is symmetric about the tool's x–z plane: reversing the spin is that
    mirror, so only the lateral force changes, its sign."""
    parallel = [c for c in cases if c.orientation == "parallel"]
    fwd = Sensitivities(ModelSetup(spin="forward")).predict(parallel, US, K)
    rev = Sensitivities(ModelSetup(spin="reverse")).predict(parallel, US, K)
    assert np.allclose(rev[:, [0, 2]], fwd[:, [0, 2]])
    assert np.allclose(rev[:, 1], -fwd[:, 1])


# -- recovery -----------------------------------------------------------------------------------
@pytest.mark.parametrize("fit_k", [True, False])
def test_noise_free_forces_give_back_us_and_k_exactly(sens, cases, fit_k):
    est = fit_rows(_rows(sens, cases, us=1610.0, k=0.9), sens,
                   FitOptions(fit_k=fit_k, k=0.9))
    assert est.us == pytest.approx(1610.0, rel=1e-9)
    assert est.k == pytest.approx(0.9, rel=1e-9)
    assert est.rmse_N < 1e-9


def test_noisy_forces_give_us_and_k_inside_their_intervals(sens, cases):
    cal = calibrate(_rows(sens, cases, noise_N=0.05, seed=3), FitOptions(), sens)
    d = cal.as_dict()
    assert d["us_ci"][0] < US < d["us_ci"][1]
    assert d["k_ci"][0] < K < d["k_ci"][1]
    assert d["rmse_N"] == pytest.approx(0.05, rel=0.2)
    assert d["n_observations"] == 135 and d["dof"] == 133


def _scattered_rows(sens, cases, rng, replicates=5, scatter=0.1, noise_N=0.03):
    """Replicates that differ as a whole (a deeper or shallower run) plus sensor noise."""
    model = sens.predict(cases, US, K)
    return [CaseRow(c, *(m * (1.0 + scatter * rng.standard_normal())
                         + noise_N * rng.standard_normal(3)).tolist())
            for c, m in zip(cases, model, strict=True) for _ in range(replicates)]


@pytest.mark.parametrize("fit_k", [True, False])
@pytest.mark.parametrize("scatter", [0.0, 0.1])
def test_the_intervals_cover_the_truth_as_often_as_they_claim(sens, cases, fit_k, scatter):
    """200 datasets with sensor noise, with and without replicate scatter: the 95 % intervals
    of Us (t) and K (Fieller) cover the truth close to 95 % of the time (binomial sd 1.5 %)."""
    covered_us = covered_k = 0
    trials = 200
    for seed in range(trials):
        rows = _scattered_rows(sens, cases, np.random.default_rng(seed), replicates=3,
                               scatter=scatter, noise_N=0.1 if scatter == 0.0 else 0.03)
        est = fit_rows(rows, sens, FitOptions(fit_k=fit_k))
        assert est.intervals == "replicate"
        covered_us += est.us_ci[0] <= US <= est.us_ci[1]
        covered_k += fit_k and est.k_ci[0] <= K <= est.k_ci[1]
    assert 0.90 <= covered_us / trials <= 0.99
    if fit_k:
        assert 0.90 <= covered_k / trials <= 0.99


def test_textbook_intervals_are_overconfident_under_replicate_scatter(sens, cases):
    """Why the default is cluster-robust: a whole-run scatter makes a row's three components
    move together, and the intervals that count them as independent cover far too rarely."""
    covered = {"replicate": 0, "ols": 0}
    trials = 200
    for seed in range(trials):
        rows = _scattered_rows(sens, cases, np.random.default_rng(seed))
        for kind in covered:
            est = fit_rows(rows, sens, FitOptions(fit_k=False, intervals=kind))
            covered[kind] += est.us_ci[0] <= US <= est.us_ci[1]
    assert covered["ols"] / trials < 0.85
    assert 0.90 <= covered["replicate"] / trials <= 0.99


def test_few_rows_fall_back_to_textbook_intervals_and_say_so(sens, cases):
    cal = calibrate(_rows(sens, cases[:4], replicates=1, noise_N=0.02), FitOptions(), sens)
    assert cal.estimate.intervals == "ols"
    assert any("too few for intervals robust" in w for w in cal.warnings)


def test_fieller_matches_the_delta_method_when_us_is_sharp():
    cov = np.array([[1e-4, 0.0], [0.0, 1e-4]])
    (lo, hi), bounded = fieller(800.0, 1040.0, cov, 1.96)
    assert bounded
    half_delta = 1.96 * math.sqrt(1e-4 * (1 + 1.3 ** 2)) / 800.0
    assert lo == pytest.approx(1.3 - half_delta, rel=1e-6)
    assert hi == pytest.approx(1.3 + half_delta, rel=1e-6)


def test_fieller_is_unbounded_when_us_is_not_clearly_nonzero():
    (lo, hi), bounded = fieller(1.0, 1.3, np.eye(2), 1.96)
    assert not bounded and lo == -math.inf and hi == math.inf


# -- cross-validation ---------------------------------------------------------------------------
def test_thesis_validation_fits_parallel_and_perpendicular_and_predicts_diagonal(sens, cases):
    rows = _rows(sens, cases, noise_N=0.02, seed=5)
    # A diagonal offset the training fit cannot see.
    rows = [CaseRow(r.case, r.feed_N + (0.2 if r.case.orientation == "diagonal" else 0.0),
                    r.lateral_N, r.normal_N) for r in rows]
    t = calibrate(rows, FitOptions(), sens).thesis_validation
    assert t["train_rows"] == 30 and t["test_rows"] == 15
    assert t["us"] == pytest.approx(US, rel=0.02)
    # 0.2 N on one of three components, over the three diagonal cases.
    assert t["mean_differential_N"] == pytest.approx(0.2 / 3, abs=0.015)
    assert t["per_component_rmse_N"]["feed"] == pytest.approx(0.2, abs=0.02)


def test_leave_one_case_out_holds_out_whole_cases(sens, cases):
    loo = calibrate(_rows(sens, cases, noise_N=0.02, seed=6), FitOptions(), sens).leave_one_out
    assert len(loo["folds"]) == 9
    assert loo["us_range"][0] < US < loo["us_range"][1]
    assert loo["rmse_N"] == pytest.approx(0.02, rel=0.5)


def test_cross_validation_says_why_it_was_skipped(sens, cases):
    rows = _rows(sens, [c for c in cases if c.orientation == "parallel"], noise_N=0.01)
    d = calibrate(rows, FitOptions(), sens).as_dict()
    assert "diagonal rows" in d["cross_validation"]["thesis"]["skipped"]
    assert len(d["cross_validation"]["leave_one_out"]["folds"]) == 3


# -- what cannot be fitted ----------------------------------------------------------------------
def test_forces_on_the_workpiece_are_refused_with_the_reason(sens, cases):
    rows = [CaseRow(r.case, -r.feed_N, -r.lateral_N, -r.normal_N)
            for r in _rows(sens, cases, noise_N=0.01)]
    with pytest.raises(FitError, match="ON THE BURR"):
        calibrate(rows, FitOptions(), sens)


def test_one_flipped_axis_is_warned_about(sens, cases):
    rows = [CaseRow(r.case, r.feed_N, -r.lateral_N, r.normal_N)
            for r in _rows(sens, cases, noise_N=0.01)]
    warnings = calibrate(rows, FitOptions(fit_k=False), sens).warnings
    assert len(warnings) == 1 and warnings[0].startswith("lateral")


def test_a_replicate_recorded_the_other_way_round_is_named(sens, cases):
    rows = _rows(sens, cases, noise_N=0.01)
    rows[4] = CaseRow(rows[4].case, -rows[4].feed_N, -rows[4].lateral_N, -rows[4].normal_N,
                      source="run-5.csv")
    warnings = calibrate(rows, FitOptions(), sens).warnings
    assert any("1 row(s) oppose the model in every component: run-5.csv" in w
               for w in warnings)


def test_a_negative_k_and_an_interval_reaching_zero_are_warned_about(sens, cases):
    pulled_in = [CaseRow(r.case, r.feed_N, r.lateral_N, -r.normal_N)
                 for r in _rows(sens, cases, noise_N=0.01)]
    cal = calibrate(pulled_in, FitOptions(), sens)
    assert cal.estimate.k < 0 and any("K = " in w and "negative" in w for w in cal.warnings)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_forces_that_are_mostly_noise_are_warned_about_or_refused(sens, cases, sign):
    """Noise with a trace of the model's signs: the fitted Us is small and its interval
    reaches 0, which is warned about; the same rows negated give exactly the opposite Us (the
    fit is linear in the forces), ≤ 0, which is refused. Both branches are asserted, whichever
    sign the noise happens to favour."""
    rng = np.random.default_rng(0)
    noise = [CaseRow(c, *(0.02 * rng.standard_normal(3) + [-0.001, 0.0, 0.001]))
             for c in cases for _ in range(2)]
    options = FitOptions(fit_k=False)
    us = fit_rows(noise, sens, options).us  # the seed's noise favours the model's signs
    assert us > 0.0
    rows = [CaseRow(r.case, sign * r.feed_N, sign * r.lateral_N, sign * r.normal_N)
            for r in noise]
    if sign > 0.0:
        cal = calibrate(rows, options, sens)
        assert cal.estimate.us == us
        assert any("barely determine Us" in w for w in cal.warnings)
    else:
        with pytest.raises(FitError, match=r"Us = -.* ≤ 0"):
            calibrate(rows, options, sens)


def test_nearly_exact_data_keep_a_bounded_k_interval(sens, cases):
    """Rounding used to make Fieller's discriminant a hair negative on proportional data and
    report K's interval as unbounded while Us sat 68 standard errors from zero."""
    nineties = [c for c in cases if c.angle_deg == 90.0]
    rows = _rows(sens, nineties, replicates=5, noise_N=0.0)
    rows = [CaseRow(r.case, r.feed_N * (1 + 0.01 * i), r.lateral_N * (1 + 0.01 * i),
                    r.normal_N * (1 + 0.01 * i)) for i, r in enumerate(rows)]
    est = fit_rows(rows, sens, FitOptions())
    assert est.k_ci_bounded and est.k_ci[0] <= est.k <= est.k_ci[1]


def test_too_little_data_is_refused(sens, cases):
    with pytest.raises(FitError, match="cannot fit 2"):
        fit_rows(_rows(sens, cases[:1], replicates=1)[:1], sens,
                 FitOptions(components=("feed", "normal")))
    with pytest.raises(FitError, match="cannot tell Us from Us·K"):
        fit_rows(_rows(sens, cases[:1], replicates=4, noise_N=0.01), sens,
                 FitOptions(components=("feed",)))
    with pytest.raises(FitError, match="no rows"):
        calibrate([], FitOptions(), sens)
    with pytest.raises(ValueError, match="components"):
        FitOptions(components=("feed", "torque"))


# -- the case table ---------------------------------------------------------------------------
def test_the_case_table_round_trips(tmp_path, sens, cases):
    rows = _rows(sens, cases, replicates=2, noise_N=0.1)
    rows[0] = CaseRow(rows[0].case, rows[0].feed_N, rows[0].lateral_N, rows[0].normal_N,
                      source="run-1.csv")
    back = read_case_table(write_case_table(tmp_path / "cases.csv", rows))
    assert back == rows and back[0].source == "run-1.csv"


def test_the_case_table_takes_semicolons_comments_and_any_column_order():
    text = ("# from the lab notebook\n"
            "normal_N;feed_N;lateral_N;orientation;angle_deg;depth_mm;feed_mm_s;rpm;radius_mm;"
            "operator\n"
            "0.9;-0.5;0.05;Parallel;60;0.5;3;60000;2;ann\n")
    (row,) = parse_case_table(text)
    assert row.case.orientation == "parallel" and row.normal_N == 0.9 and row.feed_N == -0.5


@pytest.mark.parametrize("text, message", [
    ("", "no header and no rows"),
    ("orientation,angle_deg\nparallel,30\n", "lacks depth_mm"),
    (",".join(COLUMNS) + "\n", "a header but no rows"),
    (",".join(COLUMNS) + "\nsideways,30,0.5,3,60000,2,0,0,0\n", "line 2: orientation"),
    (",".join(COLUMNS) + "\nparallel,thirty,0.5,3,60000,2,0,0,0\n",
     "line 2: angle_deg is not a number"),
    (",".join(COLUMNS) + "\nparallel,30,0.5,3,60000,2,nan,0,0\n", "feed_N must be finite"),
    (",".join(COLUMNS) + "\nparallel,30,0.5,3,60000,2,0,0\n", "8 cells, the header has 9"),
    (",".join(COLUMNS) + "\nparallel,120,0.5,3,60000,2,0,0,0\n", "angle_deg must be in"),
    (",".join(COLUMNS) + "\nparallel,30,0.5,3,-60000,2,0,0,0\n", "rpm must be > 0"),
    (",".join(COLUMNS) + "\nparallel,30,0.5,3,60000,2,5e7,0,0\n", "beyond"),
    (",".join(COLUMNS) + ",rpm\n", "rpm appears twice"),
])
def test_bad_case_tables_say_what_is_wrong(text, message):
    with pytest.raises(CaseTableError, match=message):
        parse_case_table(text, "t.csv")


def test_an_unreadable_case_table_is_a_clear_error(tmp_path):
    with pytest.raises(CaseTableError, match="cannot read"):
        read_case_table(tmp_path / "absent.csv")
    (tmp_path / "bin.csv").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(CaseTableError, match="cannot read"):
        read_case_table(tmp_path / "bin.csv")


@settings(max_examples=examples(200), deadline=None)
@given(st.text(max_size=300))
def test_any_text_is_a_table_or_a_case_table_error(text):
    try:
        parse_case_table(",".join(COLUMNS) + "\n" + text)
    except CaseTableError:
        pass


# -- the plot -----------------------------------------------------------------------------------
def test_the_plot_is_the_thesis_figure(tmp_path, sens, cases):
    import matplotlib.image

    cal = calibrate(_rows(sens, cases, noise_N=0.05), FitOptions(), sens)
    path = tmp_path / "sub" / "fit.png"
    from burrforce.server.calib.plot import plot_calibration

    assert plot_calibration(cal, path, sens) == path
    image = matplotlib.image.imread(path)
    assert image.shape[0] > 800 and image.shape[1] > 1000  # 3 × 3 panels
