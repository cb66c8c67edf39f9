"""Fitting Us, or Us and K, to measured mean forces by linear least squares (model.md).

Each measured component ``y`` of a case is modelled as ``y = Us·a + (Us·K)·b`` with the case's
sensitivities ``a``, ``b`` (:mod:`.design`). With K known this is a one-column regression through
the origin; with K free, a two-column one in θ = (Us, Us·K). Both have closed-form answers.
K = θ₂/θ₁ gets Fieller's interval, exact for a ratio of normally distributed estimates (it is
unbounded when Us is not clearly non-zero, and reported so).

The intervals are cluster-robust by replicate (a sandwich covariance with each table row a
cluster, t with rows − 1 degrees of freedom). Real replicates differ as a whole — a deeper cut
raises every component at once — so the three components of one row are not independent
observations; in a test with 10 % replicate scatter (tests/test_calib_fit.py) the textbook
intervals that assume they are covered the truth 72.5 % of the time for a 95 % claim, the
cluster-robust ones 96 %. ``intervals="ols"`` gives the textbook ones; with fewer than
:data:`MIN_CLUSTERS` rows they are used anyway, with a warning.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .design import Sensitivities
from .table import COMPONENTS, CaseRow, group_rows

DEFAULT_CONFIDENCE = 0.95
#: Fewer replicate rows than this make a cluster-robust covariance unreliable.
MIN_CLUSTERS = 6
INTERVALS = ("replicate", "ols")


class FitError(ValueError):
    """The data cannot determine the requested parameters; the message says why."""


@dataclass(frozen=True)
class FitOptions:
    """What to fit and on what.

    Attributes:
        fit_k: fit K as well as Us; otherwise K is held at ``k``.
        k: K when it is held fixed.
        components: the force components used, a subset of feed, lateral, normal.
        confidence: the confidence level of the intervals, in (0, 1).
        intervals: "replicate" (cluster-robust by table row) or "ols" (independent
            observations).
    """

    fit_k: bool = True
    k: float = 1.3
    components: tuple[str, ...] = COMPONENTS
    confidence: float = DEFAULT_CONFIDENCE
    intervals: str = "replicate"

    def __post_init__(self) -> None:
        bad = [c for c in self.components if c not in COMPONENTS]
        if bad or not self.components or len(set(self.components)) != len(self.components):
            raise ValueError(f"components must be distinct names among {', '.join(COMPONENTS)}, "
                             f"got {', '.join(self.components) or 'none'}")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must be in (0, 1), got {self.confidence}")
        if not (math.isfinite(self.k) and 0.0 <= self.k <= 100.0):
            raise ValueError(f"k must be in [0, 100], got {self.k}")
        if self.intervals not in INTERVALS:
            raise ValueError(f"intervals must be one of {', '.join(INTERVALS)}, "
                             f"got {self.intervals!r}")

    @property
    def columns(self) -> list[int]:
        return [COMPONENTS.index(c) for c in self.components]


@dataclass(frozen=True)
class Estimate:
    """The least-squares answer on one set of rows."""

    us: float
    k: float
    us_se: float
    us_ci: tuple[float, float]
    k_ci: tuple[float, float] | None        # None: K held fixed
    k_ci_bounded: bool
    cov: np.ndarray                         # (p, p) covariance of θ = (Us[, Us·K])
    sigma_N: float                          # residual standard error, √(RSS/dof)
    rmse_N: float                           # √(RSS/n)
    n_observations: int
    dof: int
    intervals: str                          # what the intervals are: replicate or ols


@dataclass
class Calibration:
    """A fit with its residuals and cross-validation (``as_dict`` is the ``--json`` form)."""

    options: FitOptions
    estimate: Estimate
    rows: list[CaseRow]
    predicted_N: np.ndarray                 # (n_rows, 3) model at the fit, every component
    residual_stats: dict[str, dict[str, float]]
    per_case: list[dict]
    thesis_validation: dict
    leave_one_out: dict
    warnings: list[str] = field(default_factory=list)

    def summary(self) -> dict:
        """The estimates and their quality without the per-case detail: what is worth keeping
        beside applied values."""
        return summary_of(self.as_dict())

    def as_dict(self) -> dict:
        e = self.estimate
        return {
            "us": e.us, "k": e.k,
            "us_ci": list(e.us_ci),
            "k_ci": list(e.k_ci) if e.k_ci is not None and e.k_ci_bounded else None,
            "k_fixed": not self.options.fit_k,
            "us_se": e.us_se,
            "rmse_N": e.rmse_N, "sigma_N": e.sigma_N,
            "confidence": self.options.confidence, "intervals": e.intervals,
            "components": list(self.options.components),
            "n_rows": len(self.rows), "n_cases": len(self.per_case),
            "n_observations": e.n_observations, "dof": e.dof,
            "residuals": self.residual_stats,
            "cases": self.per_case,
            "cross_validation": {"thesis": self.thesis_validation,
                                 "leave_one_out": self.leave_one_out},
            "warnings": self.warnings,
        }


SUMMARY_KEYS = ("us", "k", "us_ci", "k_ci", "k_fixed", "us_se", "rmse_N", "sigma_N",
                "confidence", "intervals", "components", "n_rows", "n_cases", "n_observations")


def summary_of(result: dict) -> dict:
    """The :meth:`Calibration.summary` part of an ``as_dict`` result."""
    return {key: result[key] for key in SUMMARY_KEYS}


def estimate(y: np.ndarray, a: np.ndarray, b: np.ndarray, options: FitOptions) -> Estimate:
    """Least squares on observations ``y`` (rows, components) with sensitivities ``a``, ``b``
    of the same shape; each row is one replicate (a cluster for the intervals).

    Raises:
        FitError: fewer observations than parameters plus one, sensitivities that cannot
            separate Us from Us·K, or a fit with Us ≤ 0 (forces of the wrong sign).
    """
    fit_k = options.fit_k
    x3 = np.stack([a, b], axis=-1) if fit_k else (a + options.k * b)[..., None]
    g, per_row, p = x3.shape
    x = x3.reshape(-1, p)
    yf = y.ravel()
    m = x.shape[0]
    if m <= p:
        raise FitError(f"{m} observation(s) cannot fit {p} parameter(s) with an uncertainty: "
                       f"add replicates, cases or components")
    # Scale the columns so the conditioning test means what it says.
    norms = np.linalg.norm(x, axis=0)
    if (norms == 0.0).any():
        raise FitError("the model predicts no force for the components used, so they say "
                       "nothing about Us")
    xs = x / norms
    if np.linalg.cond(xs) > 1e6:
        raise FitError("these cases cannot tell Us from Us·K: the normal and tangential parts "
                       "move together in every observation. Add cutting angles or "
                       "orientations, or fit Us alone with K fixed")
    theta_s, *_ = np.linalg.lstsq(xs, yf, rcond=None)
    theta = theta_s / norms
    resid = yf - x @ theta
    rss = float(resid @ resid)
    dof = m - p
    bread = np.linalg.inv(x.T @ x)
    intervals = options.intervals if g >= MIN_CLUSTERS else "ols"
    if intervals == "replicate":
        # CR1 sandwich: Σ over rows of (Xᵣᵀeᵣ)(Xᵣᵀeᵣ)ᵀ, small-sample corrected.
        scores = np.einsum("gcp,gc->gp", x3, resid.reshape(g, per_row))
        meat = scores.T @ scores
        correction = g / (g - 1) * (m - 1) / (m - p)
        cov = correction * bread @ meat @ bread
        t_dof = g - 1
    else:
        cov = rss / dof * bread
        t_dof = dof
    # Here, not at the top: scipy.stats takes ~0.6 s to import, and every `serve` imports
    # this module (the calibration routes) but few fit anything.
    from scipy import stats

    t = float(stats.t.ppf(0.5 + options.confidence / 2.0, t_dof))
    us = float(theta[0])
    if us <= 0.0:
        raise FitError(
            f"the best fit has Us = {us:.4g} N/mm² ≤ 0: the measured forces oppose the model's. "
            "The table holds the bone's force ON THE BURR (model.md: feed and normal force are "
            "negative and positive in steady cutting); a dynamometer under the bone measures "
            "the opposite (use forces_on = workpiece)")
    us_se = math.sqrt(cov[0, 0])
    us_ci = (us - t * us_se, us + t * us_se)
    if fit_k:
        k = float(theta[1] / theta[0])
        k_ci, bounded = fieller(theta[0], theta[1], cov, t)
    else:
        k, k_ci, bounded = options.k, None, True
    return Estimate(us=us, k=k, us_se=us_se, us_ci=us_ci, k_ci=k_ci, k_ci_bounded=bounded,
                    cov=cov, sigma_N=math.sqrt(rss / dof), rmse_N=math.sqrt(rss / m),
                    n_observations=m, dof=dof, intervals=intervals)


def fieller(t1: float, t2: float, cov: np.ndarray, t: float) -> tuple[tuple[float, float], bool]:
    """Fieller's confidence interval for ρ = θ₂/θ₁.

    The set of ρ with (θ₂ − ρθ₁)² ≤ t²·var(θ₂ − ρθ₁) is an interval only when θ₁ is
    significantly non-zero (t₁² > t²·V₁₁); otherwise it is unbounded and the second value is
    False (the first is then (−inf, inf)).
    """
    v11, v12, v22 = cov[0, 0], cov[0, 1], cov[1, 1]
    qa = t1 * t1 - t * t * v11
    qb = -2.0 * (t1 * t2 - t * t * v12)
    qc = t2 * t2 - t * t * v22
    if qa <= 0.0:
        return (-math.inf, math.inf), False
    # With qa > 0 the discriminant is ≥ 0 in exact arithmetic (the estimate itself lies in the
    # set); rounding can push it a hair below zero on nearly noise-free data, and leave the
    # estimate an ulp outside the interval that is then almost a point: it is kept inside.
    disc = max(qb * qb - 4.0 * qa * qc, 0.0)
    root = math.sqrt(disc)
    rho = t2 / t1
    lo = min((-qb - root) / (2.0 * qa), rho)
    hi = max((-qb + root) / (2.0 * qa), rho)
    return (float(lo), float(hi)), True


def _stack(rows: Sequence[CaseRow], sens: Sensitivities, columns: list[int]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a, b = sens.matrices([r.case for r in rows])
    y = np.array([r.forces_N for r in rows])
    return y[:, columns], a[:, columns], b[:, columns]


def fit_rows(rows: Sequence[CaseRow], sens: Sensitivities, options: FitOptions) -> Estimate:
    """The least-squares estimate on these rows."""
    return estimate(*_stack(rows, sens, options.columns), options)


def calibrate(rows: Sequence[CaseRow], options: FitOptions | None = None,
              sens: Sensitivities | None = None) -> Calibration:
    """Fit, then describe the residuals and cross-validate.

    Raises:
        FitError: the rows cannot determine the parameters (see :func:`estimate`).
        ValueError: a case the model cannot evaluate (e.g. below the cutting speed).
    """
    options = options if options is not None else FitOptions()
    sens = sens if sens is not None else Sensitivities()
    rows = list(rows)
    if not rows:
        raise FitError("no rows to fit")
    est = fit_rows(rows, sens, options)
    cases = [r.case for r in rows]
    predicted = sens.predict(cases, est.us, est.k)
    measured = np.array([r.forces_N for r in rows])
    return Calibration(
        options=options, estimate=est, rows=rows, predicted_N=predicted,
        residual_stats=_residual_stats(measured - predicted, options),
        per_case=_per_case(rows, predicted),
        thesis_validation=thesis_validation(rows, sens, options),
        leave_one_out=leave_one_case_out(rows, sens, options),
        warnings=_sign_warnings(rows, predicted, options) + _estimate_warnings(est, options)
        + ([
            f"{len(rows)} rows are too few for intervals robust to replicate scatter (need "
            f"{MIN_CLUSTERS}): these assume independent observations"]
            if est.intervals != options.intervals else []),
    )


def _residual_stats(resid: np.ndarray, options: FitOptions) -> dict[str, dict[str, float]]:
    """Per component: RMSE, mean (bias) and largest absolute residual, N. Components left out
    of the fit are reported too (marked), since a model that misses them is worth knowing."""
    out = {}
    for j, name in enumerate(COMPONENTS):
        r = resid[:, j]
        out[name] = {"rmse_N": float(np.sqrt(np.mean(r * r))), "bias_N": float(r.mean()),
                     "max_abs_N": float(np.abs(r).max()),
                     "fitted": name in options.components}
    return out


def _per_case(rows: Sequence[CaseRow], predicted: np.ndarray) -> list[dict]:
    index = {id(r): i for i, r in enumerate(rows)}
    out = []
    for group in group_rows(rows).values():
        idx = [index[id(r)] for r in group]
        measured = np.array([r.forces_N for r in group])
        c = group[0].case
        entry = {
            "orientation": c.orientation, "angle_deg": c.angle_deg, "depth_mm": c.depth_mm,
            "feed_mm_s": c.feed_mm_s, "rpm": c.rpm, "radius_mm": c.radius_mm,
            "replicates": len(group),
        }
        for j, name in enumerate(COMPONENTS):
            entry[f"{name}_N"] = float(measured[:, j].mean())
            entry[f"{name}_sd_N"] = float(measured[:, j].std(ddof=1)) if len(group) > 1 else None
            entry[f"{name}_model_N"] = float(predicted[idx[0], j])
        out.append(entry)
    return out


def _sign_warnings(rows: Sequence[CaseRow], predicted: np.ndarray,
                   options: FitOptions) -> list[str]:
    """Flag a fitted component whose measured means mostly have the opposite sign to the model:
    the usual cause is a flipped axis or the force on the workpiece instead of on the burr."""
    measured = np.array([r.forces_N for r in rows])
    warnings = []
    cols = options.columns
    clear = np.abs(predicted[:, cols]) > 0.05 * np.abs(predicted[:, cols]).max()
    opposed_rows = [r.source or f"row {i + 1}" for i, r in enumerate(rows)
                    if clear[i].sum() >= 2 and (np.sign(measured[i, cols][clear[i]])
                                                == -np.sign(predicted[i, cols][clear[i]])).all()]
    if opposed_rows and len(opposed_rows) < len(rows):
        shown = ", ".join(opposed_rows[:5]) + (" …" if len(opposed_rows) > 5 else "")
        warnings.append(
            f"{len(opposed_rows)} row(s) oppose the model in every component: {shown} — "
            "recorded on the burr rather than the workpiece (or the reverse)?")
    for j in options.columns:
        clear = np.abs(predicted[:, j]) > 0.05 * np.abs(predicted[:, j]).max()
        if clear.sum() < 2:
            continue
        opposed = np.sign(measured[clear, j]) != np.sign(predicted[clear, j])
        if opposed.mean() > 0.5:
            warnings.append(
                f"{COMPONENTS[j]}: {int(opposed.sum())} of {int(clear.sum())} measurements "
                "have the opposite sign to the model — check the axis and that the forces are "
                "on the burr (model.md)")
    return warnings


def _estimate_warnings(est: Estimate, options: FitOptions) -> list[str]:
    warnings = []
    if est.us_ci[0] <= 0.0:
        warnings.append(
            f"the Us interval reaches {est.us_ci[0]:.4g} ≤ 0: the data barely determine Us. "
            "Check the axes and forces_on of every recording (a swapped axis or a replicate "
            "of the wrong sign does this), or add cases")
    if options.fit_k and est.k < 0.0:
        warnings.append(
            f"the fitted K = {est.k:.4g} is negative, which no material has (the normal force "
            "would pull the burr in): check the normal axis's sign, or fit Us alone")
    return warnings


def _prediction_errors(train: Sequence[CaseRow], test: Sequence[CaseRow], sens: Sensitivities,
                       options: FitOptions) -> tuple[Estimate, np.ndarray]:
    est = fit_rows(train, sens, options)
    predicted = sens.predict([r.case for r in test], est.us, est.k)
    measured = np.array([r.forces_N for r in test])
    return est, (measured - predicted)[:, options.columns]


def thesis_validation(rows: Sequence[CaseRow], sens: Sensitivities,
                      options: FitOptions) -> dict:
    """The thesis's check: fit on parallel + perpendicular, predict diagonal.

    Reports the training fit, the prediction RMSE and the mean magnitude differential (the
    thesis reports ≈ 0.2 N): the mean over diagonal cases and components of |measured mean −
    model|.
    """
    train = [r for r in rows if r.case.orientation in ("parallel", "perpendicular")]
    test = [r for r in rows if r.case.orientation == "diagonal"]
    if not train or not test:
        have = sorted({r.case.orientation for r in rows})
        return {"skipped": "needs parallel or perpendicular rows to fit and diagonal rows to "
                           f"predict; the table has {', '.join(have)}"}
    try:
        est, err = _prediction_errors(train, test, sens, options)
    except FitError as exc:
        return {"skipped": f"parallel + perpendicular alone cannot be fitted: {exc}"}
    groups = group_rows(test)
    predicted = sens.predict([g[0].case for g in groups.values()], est.us, est.k)
    means = np.array([np.mean([r.forces_N for r in g], axis=0) for g in groups.values()])
    diff = np.abs(means - predicted)[:, options.columns]
    return {
        "us": est.us, "k": est.k, "us_ci": list(est.us_ci),
        "k_ci": list(est.k_ci) if est.k_ci is not None and est.k_ci_bounded else None,
        "train_rows": len(train), "test_rows": len(test),
        "rmse_N": float(np.sqrt(np.mean(err * err))),
        "mean_differential_N": float(diff.mean()),
        "per_component_rmse_N": {options.components[i]: float(np.sqrt(np.mean(err[:, i] ** 2)))
                                 for i in range(err.shape[1])},
    }


def leave_one_case_out(rows: Sequence[CaseRow], sens: Sensitivities,
                       options: FitOptions) -> dict:
    """Hold out each case (all its replicates) in turn, fit the rest, predict it.

    Holding out whole cases, not single replicates, keeps a case's other replicates from
    vouching for it. Each fold is the full fit's normal equations minus the held-out rows'
    share, so the folds together cost one pass over the table.
    """
    groups = group_rows(rows)
    if len(groups) < 2:
        return {"skipped": "needs at least two cases"}
    y, a, b = _stack(rows, sens, options.columns)
    x = np.stack([a, b], axis=-1) if options.fit_k else (a + options.k * b)[..., None]
    p = x.shape[-1]
    xtx = np.einsum("rcp,rcq->pq", x, x)
    xty = np.einsum("rcp,rc->p", x, y)
    index = {id(r): i for i, r in enumerate(rows)}
    folds, errors, skipped = [], [], []
    for held in groups.values():
        idx = [index[id(r)] for r in held]
        xg, yg = x[idx].reshape(-1, p), y[idx].ravel()
        c = held[0].case
        label = f"{c.orientation} {c.angle_deg:g}°"
        rest = xtx - xg.T @ xg
        if len(rows) - len(idx) < 1 or np.linalg.cond(rest) > 1e12:
            skipped.append(f"{label}: the other cases cannot determine the parameters")
            continue
        theta = np.linalg.solve(rest, xty - xg.T @ yg)
        if theta[0] <= 0.0:
            skipped.append(f"{label}: the other cases give Us ≤ 0")
            continue
        err = yg - xg @ theta
        errors.append(err)
        k = float(theta[1] / theta[0]) if options.fit_k else options.k
        folds.append({"case": label, "us": float(theta[0]), "k": k,
                      "rmse_N": float(np.sqrt(np.mean(err * err)))})
    if not folds:
        return {"skipped": "no fold could be fitted: " + "; ".join(skipped)}
    all_err = np.concatenate(errors)
    us = np.array([f["us"] for f in folds])
    out = {
        "folds": folds,
        "rmse_N": float(np.sqrt(np.mean(all_err * all_err))),
        "us_range": [float(us.min()), float(us.max())],
    }
    if options.fit_k:
        k = np.array([f["k"] for f in folds])
        out["k_range"] = [float(k.min()), float(k.max())]
    if skipped:
        out["skipped_folds"] = skipped
    return out


def finite_or_none(value: object) -> object:
    """``value`` with every NaN or infinite float replaced by None, recursively: JSON has no
    NaN (``json.dumps`` would write an invalid document)."""
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
