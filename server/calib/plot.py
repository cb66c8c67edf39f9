"""The thesis's Fig. 19/20 for a calibration: measurements as box plots, the fitted model as
curves against cutting angle, a row per orientation and a column per force component."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from ..model.cases import ORIENTATIONS, CuttingCase
from ..plotting import pyplot, save_figure
from .design import Sensitivities
from .fit import Calibration
from .table import COMPONENTS

SWEEP_DEG = np.linspace(10.0, 90.0, 81)


def _sweep(sens: Sensitivities, like: CuttingCase, us: float, k: float) -> np.ndarray:
    """(len(SWEEP_DEG), 3) model components over the angle sweep, the rest as ``like``."""
    cases = [CuttingCase(like.orientation, float(a), radius_mm=like.radius_mm,
                         depth_mm=like.depth_mm, feed_mm_s=like.feed_mm_s, rpm=like.rpm)
             for a in SWEEP_DEG]
    return sens.predict(cases, us, k)


def _interval(ci: tuple[float, float] | list[float] | None, digits: str) -> str:
    return "" if ci is None else f" [{ci[0]:{digits}}, {ci[1]:{digits}}]"


def plot_calibration(cal: Calibration, path: str | Path, sens: Sensitivities | None = None
                     ) -> Path:
    """Write the PNG and return its path.

    Each orientation's curve uses its most common geometry (depth, feed, rpm, radius); boxes of
    other geometries are still drawn. With the thesis's validation available, the diagonal row
    also shows the parallel + perpendicular fit's prediction, dashed.
    """
    plt = pyplot()
    sens = sens if sens is not None else Sensitivities()
    est = cal.estimate
    present = {r.case.orientation for r in cal.rows}
    orientations = [o for o in ORIENTATIONS if o in present]
    fig, axes = plt.subplots(len(orientations), 3, figsize=(12.0, 3.4 * len(orientations)),
                             squeeze=False)
    validation = cal.thesis_validation
    geometry: list[tuple[str, str]] = []
    for i, orientation in enumerate(orientations):
        rows = [r for r in cal.rows if r.case.orientation == orientation]
        common = Counter((r.case.depth_mm, r.case.feed_mm_s, r.case.rpm, r.case.radius_mm)
                         for r in rows).most_common(1)[0][0]
        like = next(r.case for r in rows if (r.case.depth_mm, r.case.feed_mm_s, r.case.rpm,
                                             r.case.radius_mm) == common)
        curve = _sweep(sens, like, est.us, est.k)
        held_out = None
        if orientation == "diagonal" and "us" in validation:
            held_out = _sweep(sens, like, validation["us"], validation["k"])
        geometry.append((orientation, f"h = {common[0]:g} mm, {common[1]:g} mm/s, "
                                      f"{common[2]:g} rpm, R = {common[3]:g} mm"))
        angles = sorted({r.case.angle_deg for r in rows})
        for j, name in enumerate(COMPONENTS):
            ax = axes[i][j]
            data = [[r.forces_N[j] for r in rows if r.case.angle_deg == a] for a in angles]
            ax.boxplot(data, positions=angles, widths=5.0, manage_ticks=False,
                       medianprops={"color": "k"}, flierprops={"markersize": 3})
            ax.plot(SWEEP_DEG, curve[:, j], color="tab:red",
                    label="model, fitted on all" if held_out is not None else "model")
            if held_out is not None:
                ax.plot(SWEEP_DEG, held_out[:, j], "--", color="tab:blue",
                        label="model, fitted on parallel + perpendicular")
            ax.axhline(0.0, color="0.85", linewidth=0.8)
            ax.set_xlim(5.0, 95.0)
            ax.set_xticks([15, 30, 45, 60, 75, 90])
            ax.grid(True, alpha=0.3)
            ax.set_title(f"{orientation}: {name} force", fontsize=10)
            if i == len(orientations) - 1:
                ax.set_xlabel("cutting angle α (deg)")
            if j == 0:
                ax.set_ylabel("force on the burr (N)")
            if held_out is not None and j == 0:
                ax.legend(loc="best", fontsize=7)
    if len({g for _, g in geometry}) == 1:
        curves = geometry[0][1]
    else:
        curves = "; ".join(f"{o}: {g}" for o, g in geometry)
    k_text = (f"K = {est.k:.3g}{_interval(est.k_ci if est.k_ci_bounded else None, '.3g')}"
              if cal.options.fit_k else f"K = {est.k:g} (fixed)")
    level = f"{100.0 * cal.options.confidence:g} %"
    fig.suptitle(f"Us = {est.us:.4g}{_interval(est.us_ci, '.4g')} N/mm², {k_text} "
                 f"({level} intervals); RMSE {est.rmse_N:.3g} N over {est.n_observations} "
                 f"observations ({', '.join(cal.options.components)})\n"
                 f"curves: {curves}", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)
