"""Plain-text reports of a calibration and of processed recordings."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .fit import Calibration
from .table import COMPONENTS

if TYPE_CHECKING:
    from .folder import FolderResult


def _ci(ci: list[float] | tuple[float, float] | None, fmt: str) -> str:
    return "unbounded (Us not clearly above zero)" if ci is None else \
        f"[{ci[0]:{fmt}}, {ci[1]:{fmt}}]"


def format_calibration(cal: Calibration) -> str:
    d = cal.as_dict()
    e = cal.estimate
    level = f"{100.0 * cal.options.confidence:g} %"
    kind = ("robust to replicate scatter" if e.intervals == "replicate"
            else "observations taken as independent")
    lines = [
        f"fit on {d['n_rows']} rows ({d['n_cases']} cases), {', '.join(d['components'])}: "
        f"{d['n_observations']} observations, {d['dof']} degrees of freedom",
        f"  Us = {e.us:.5g} N/mm²   {level} CI {_ci(d['us_ci'], '.5g')}   (se {e.us_se:.3g})",
        (f"  K  = {e.k:.4g}   {level} CI {_ci(d['k_ci'], '.4g')}" if not d["k_fixed"]
         else f"  K  = {e.k:g} (held fixed)"),
        f"  RMSE {e.rmse_N:.4g} N   residual sd {e.sigma_N:.4g} N   (intervals {kind})",
        "",
        "residuals, N          rmse      bias   max |r|",
    ]
    for name in COMPONENTS:
        r = d["residuals"][name]
        mark = "" if r["fitted"] else "   (not fitted)"
        lines.append(f"  {name:<16}{r['rmse_N']:>10.4f}{r['bias_N']:>10.4f}"
                     f"{r['max_abs_N']:>10.4f}{mark}")
    lines += ["", "per case, N (measured mean ± sd / model)"]
    lines.append(f"  {'orientation':<14}{'α°':>5}{'n':>4}"
                 + "".join(f"{c:>24}" for c in COMPONENTS))
    for c in d["cases"]:
        cells = []
        for name in COMPONENTS:
            sd = c[f"{name}_sd_N"]
            sd_text = f"±{sd:.3f}" if sd is not None else "      "
            cells.append(f"{c[f'{name}_N']:>8.3f}{sd_text:>7} /{c[f'{name}_model_N']:>7.3f}")
        lines.append(f"  {c['orientation']:<14}{c['angle_deg']:>5g}{c['replicates']:>4}"
                     + "".join(f"{cell:>24}" for cell in cells))
    lines += ["", "cross-validation"]
    t = d["cross_validation"]["thesis"]
    if "skipped" in t:
        lines.append(f"  fit parallel + perpendicular, predict diagonal: skipped: {t['skipped']}")
    else:
        k_text = "" if d["k_fixed"] else f", K = {t['k']:.4g}"
        lines.append(f"  fit parallel + perpendicular ({t['train_rows']} rows): Us = "
                     f"{t['us']:.5g} {_ci(t['us_ci'], '.5g')}{k_text}")
        lines.append(f"    predicts diagonal ({t['test_rows']} rows): RMSE {t['rmse_N']:.4g} N, "
                     f"mean differential {t['mean_differential_N']:.4g} N (the thesis: ≈ 0.2 N)")
    loo = d["cross_validation"]["leave_one_out"]
    if "skipped" in loo:
        lines.append(f"  leave one case out: skipped: {loo['skipped']}")
    else:
        k_text = "" if "k_range" not in loo else \
            f", K {loo['k_range'][0]:.4g}–{loo['k_range'][1]:.4g}"
        lines.append(f"  leave one case out ({len(loo['folds'])} folds): prediction RMSE "
                     f"{loo['rmse_N']:.4g} N; Us {loo['us_range'][0]:.5g}–"
                     f"{loo['us_range'][1]:.5g}{k_text}")
    for w in d["warnings"]:
        lines.append(f"warning: {w}")
    return "\n".join(lines)


def format_recordings(result: FolderResult) -> str:
    lines = [
        f"{len(result.reports)} recording(s); mean force on the burr over the burring region, "
        "N; vibration amplitude (resultant, sinusoid fit / the thesis's peaks), N",
        f"  {'file':<22}{'orientation':<14}{'α°':>4}{'feed':>8}{'lateral':>9}{'normal':>8}"
        f"{'free':>13}{'burring':>13}{'ratio':>6}{'f Hz':>8}",
    ]
    for r in result.reports:
        a = r.analysis
        row = r.row
        lines.append(
            f"  {row.source[:21]:<22}{row.case.orientation:<14}{row.case.angle_deg:>4g}"
            f"{row.feed_N:>8.3f}{row.lateral_N:>9.3f}{row.normal_N:>8.3f}"
            f"{a.non_burring.resultant_fit_N:>7.3f}/{a.non_burring.resultant_peaks_N:<5.3f}"
            f"{a.burring.resultant_fit_N:>7.3f}/{a.burring.resultant_peaks_N:<5.3f}"
            f"{a.ratio_fit:>6.2f}{a.dominant_frequency_hz:>8.1f}")
    v = result.vibration()
    if v:
        fd_ci = "" if v["fd_ci"] is None else f" [{v['fd_ci'][0]:.3g}, {v['fd_ci'][1]:.3g}]"
        lines.append(
            f"vibration: Fd = {v['fd_N']:.4g}{fd_ci} N free-spinning, burring gain g = "
            f"{v['g']:.3g}; burring/free ratio {v['ratio_fit_mean']:.3f} (fit), "
            f"{v['ratio_peaks_mean']:.3f} (peaks); dominant frequency "
            f"{v['frequency_hz_mean']:.1f} Hz")
    for w in result.warnings:
        lines.append(f"warning: {w}")
    for f in result.failures:
        lines.append(f"skipped: {f}")
    return "\n".join(lines)
