"""The thesis's Table 1 experiment (3 orientations × 3 cutting angles), run through the model."""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .model import CuttingCase, CuttingModel, thesis_cases
from .model.cases import ORIENTATIONS
from .plotting import pyplot, save_figure


@dataclass(frozen=True)
class ExperimentRow:
    """One case's model output. Keys and units are the stable ``--json`` interface."""

    orientation: str
    angle_deg: float
    feed_N: float
    lateral_N: float
    normal_N: float
    force_N: list[float]
    torque_Nmm: list[float]
    power_W: float
    mean_speed_m_s: float

    @property
    def force_magnitude_N(self) -> float:
        return float(np.linalg.norm(self.force_N))


def run_case(model: CuttingModel, case: CuttingCase) -> ExperimentRow:
    """Evaluate one case (the model's radius must match the case's)."""
    r = model.evaluate(case.centre_mm, case.axis, case.feed_velocity_mm_s, case.rpm)
    return ExperimentRow(
        orientation=case.orientation,
        angle_deg=case.angle_deg,
        feed_N=r.feed_N,
        lateral_N=r.lateral_N,
        normal_N=r.normal_N,
        force_N=r.force_N.tolist(),
        torque_Nmm=r.torque_Nmm.tolist(),
        power_W=r.power_W,
        mean_speed_m_s=r.mean_speed_m_s,
    )


def run_experiment(
    model: CuttingModel,
    angles_deg: Sequence[float],
    depth_mm: float,
    feed_mm_s: float,
    rpm: float,
    orientations: Sequence[str] = tuple(ORIENTATIONS),
) -> list[ExperimentRow]:
    """Rows orientation-major, angle-minor, with the geometry of model.md."""
    cases = thesis_cases(angles_deg, orientations, radius_mm=model.params.radius_mm,
                         depth_mm=depth_mm, feed_mm_s=feed_mm_s, rpm=rpm)
    return [run_case(model, case) for case in cases]


def format_table(rows: Sequence[ExperimentRow]) -> str:
    """A plain-text table: components and |F| in N, mean cutting-zone speed in m/s."""
    header = (f"{'orientation':<14}{'angle°':>7}{'feed N':>10}{'lateral N':>11}"
              f"{'normal N':>10}{'|F| N':>9}{'speed m/s':>11}{'power W':>9}")
    lines = [header, "-" * len(header)]
    for r in rows:
        lines.append(
            f"{r.orientation:<14}{r.angle_deg:>7g}{r.feed_N:>10.3f}{r.lateral_N:>11.3f}"
            f"{r.normal_N:>10.3f}{r.force_magnitude_N:>9.3f}{r.mean_speed_m_s:>11.2f}"
            f"{r.power_W:>9.3f}"
        )
    return "\n".join(lines)


def rows_to_json(rows: Sequence[ExperimentRow]) -> str:
    return json.dumps([asdict(r) for r in rows], indent=2)


def plot_experiment(
    model: CuttingModel,
    rows: Sequence[ExperimentRow],
    path: Path,
    depth_mm: float,
    feed_mm_s: float,
    rpm: float,
) -> Path:
    """A PNG like the thesis's Fig. 19/20: components against cutting angle, a panel per
    orientation; model curves over a dense angle sweep, the table's angles marked."""
    plt = pyplot()
    orientations = list(dict.fromkeys(r.orientation for r in rows))
    sweep = np.linspace(10.0, 90.0, 81)
    fig, axes = plt.subplots(1, len(orientations), figsize=(4.6 * len(orientations), 4.2),
                             sharey=True, squeeze=False)
    styles = (("feed_N", "feed", "tab:blue"), ("lateral_N", "lateral", "tab:orange"),
              ("normal_N", "normal", "tab:green"))
    for ax, orientation in zip(axes[0], orientations, strict=True):
        curve = run_experiment(model, sweep, depth_mm, feed_mm_s, rpm, (orientation,))
        marks = [r for r in rows if r.orientation == orientation]
        for key, label, colour in styles:
            ax.plot(sweep, [getattr(r, key) for r in curve], color=colour, label=label)
            ax.plot([r.angle_deg for r in marks], [getattr(r, key) for r in marks], "o",
                    color=colour)
        ax.plot(sweep, [r.force_magnitude_N for r in curve], "k--", label="|F|")
        ax.axhline(0.0, color="0.8", linewidth=0.8)
        ax.set_title(f"{orientation} cutting")
        ax.set_xlabel("cutting angle α (deg)")
        ax.grid(True, alpha=0.3)
    axes[0][0].set_ylabel("resistive force on the burr (N)")
    axes[0][0].legend(loc="best", fontsize=8)
    p = model.params
    fig.suptitle(
        f"R = {p.radius_mm:g} mm, h = {depth_mm:g} mm, feed {feed_mm_s:g} mm/s, "
        f"{rpm:g} rpm {p.spin}, Us = {p.us_n_mm2:g} N/mm², K = {p.k:g}",
        fontsize=10,
    )
    fig.tight_layout()
    return save_figure(fig, path)
