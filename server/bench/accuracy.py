"""``burrforce bench accuracy``: the voxel engine's force against the analytic model, its
ripple and its time per tick, over voxel sizes and burr element counts."""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..argtypes import comma_separated, float_in
from ..model import CuttingParams, thesis_cases
from ..model.burr import DEFAULT_N_THETA
from ..model.reference import reference_case
from . import runner
from .edges import edge_rows, render_edges
from .groove import OBLIQUE_EULER_XYZ_DEG, groove_block, oblique_rotation, run_groove
from .timing import machine_line

VOXEL_SIZES_MM = (0.05, 0.1, 0.2, 0.4)
N_THETAS = (16, 24, 32)
TARGET_VOXEL_MM = 0.1
TARGET_ERROR = 0.02
TARGET_RIPPLE = 0.02
#: Carve + force per tick at the target voxel size and the default element count, aligned and
#: oblique: the median and the worst case's p99, µs.
TARGET_P50_US = 50.0
TARGET_P99_US = 100.0
EDGES_INTRO = (
    "Where a trainee spends much of the time besides the steady groove. Plunge: removal rate "
    "against the analytic spherical cap (P/Us vs v·π·(2Rh − h²)) from 10 µm deep, and the "
    "depth steps on a fine sweep where the force decreases. Retrace: the spindle power and "
    "force going back over a cut groove, as a share of the first pass's, and the widening "
    "pass's energy balance. Shapes: each burr's model against its own converged reference "
    "(`model.reference_shapes`).")


@dataclass(frozen=True)
class AccuracyRow:
    voxel_mm: float
    elements: int
    n_theta: int
    grid: str
    orientation: str
    angle_deg: float
    force_N: float
    reference_N: float
    error_rel: float
    ripple_rel: float
    tick_p50_us: float
    tick_p99_us: float


def run(voxel_sizes: tuple[float, ...], n_thetas: tuple[int, ...], oblique: bool,
        measure_mm: float, progress=None) -> list[AccuracyRow]:
    params = CuttingParams()
    cases = list(thesis_cases())
    refs = [float(np.linalg.norm(reference_case(c, params).force_N)) for c in cases]
    configs = [(v, n, "aligned") for v in voxel_sizes for n in n_thetas]
    if oblique:
        configs += [(v, DEFAULT_N_THETA, "oblique") for v in voxel_sizes]
    rows = []
    for voxel_mm, n_theta, grid_kind in configs:
        direction = oblique_rotation() if grid_kind == "oblique" else None
        for case, ref in zip(cases, refs, strict=True):
            grid = groove_block(voxel_mm, direction)
            groove = run_groove(case, grid, n_theta, measure_mm=measure_mm)
            mag = groove.magnitude_N[groove.steady]
            ticks_us = groove.tick_ns[groove.steady] / 1e3
            rows.append(AccuracyRow(
                voxel_mm=voxel_mm, elements=2 * n_theta * n_theta, n_theta=n_theta,
                grid=grid_kind, orientation=case.orientation, angle_deg=case.angle_deg,
                force_N=float(mag.mean()), reference_N=ref,
                error_rel=float(mag.mean() / ref - 1.0),
                ripple_rel=float(mag.std() / mag.mean()),
                tick_p50_us=float(np.median(ticks_us)),
                tick_p99_us=float(np.percentile(ticks_us, 99)),
            ))
            if progress is not None:
                progress(rows[-1])
    return rows


@dataclass(frozen=True)
class Summary:
    voxel_mm: float
    elements: int
    grid: str
    max_error_rel: float
    max_ripple_rel: float
    tick_p50_us: float
    tick_p99_us: float


def summarize(rows: list[AccuracyRow]) -> list[Summary]:
    """One line per (voxel size, element count, grid): worst case over the nine, and the
    median p50 / worst p99 of the tick times."""
    keys = sorted({(r.grid, r.voxel_mm, r.elements) for r in rows})
    out = []
    for grid, voxel, elements in keys:
        sel = [r for r in rows if (r.grid, r.voxel_mm, r.elements) == (grid, voxel, elements)]
        out.append(Summary(voxel, elements, grid, max(abs(r.error_rel) for r in sel),
                           max(r.ripple_rel for r in sel),
                           float(np.median([r.tick_p50_us for r in sel])),
                           max(r.tick_p99_us for r in sel)))
    return out


def rows_from_json(data: object) -> list[AccuracyRow]:
    """The result rows of an accuracy.json: a bare list (older runs) or ``{"rows": ...}``."""
    items = data.get("rows", []) if isinstance(data, dict) else data
    return [AccuracyRow(**item) for item in items]  # type: ignore[union-attr]


def load_baseline(path: Path, explicit: bool) -> tuple[list[AccuracyRow], str]:
    """The "before" rows to compare a run with, and where they came from.

    An explicit ``--baseline`` file is compared against as it is (its own results). The
    default, the accuracy.json about to be overwritten, passes on the baseline it carries, so
    a re-run keeps comparing against the first baseline instead of against itself; a file
    without one (written before baselines existed) is the baseline.
    """
    if not path.is_file():
        if explicit:
            raise FileNotFoundError(f"baseline {path} does not exist")
        return [], ""
    data = json.loads(path.read_text())
    if not explicit and isinstance(data, dict) and data.get("baseline"):
        return rows_from_json(data["baseline"]), str(data.get("baseline_source", path))
    source = data.get("source", str(path)) if isinstance(data, dict) else str(path)
    return rows_from_json(data), source


def render_markdown(rows: list[AccuracyRow], command: str, measure_mm: float,
                    baseline: list[AccuracyRow] | None = None, baseline_source: str = "") -> str:
    summary = summarize(rows)
    default = [s for s in summary if s.voxel_mm == TARGET_VOXEL_MM
               and s.elements == 2 * DEFAULT_N_THETA ** 2]
    before = {(b.grid, b.voxel_mm, b.elements): b for b in summarize(baseline or [])}
    lines = [
        "# Voxel engine: force against the analytic model, ripple, time per tick",
        "",
        f"Run: `{command}` on {dt.date.today().isoformat()}, {machine_line()}.",
        "",
        "Each case ploughs a steady groove through the workpiece block (cortical bone, "
        "Us = 805.1 N/mm², K = 1.3, flat top at z = 0, faces inside voxels: grid offset "
        "(0.31, 0.17, 0.43) voxel) with the thesis's pose: R = 2 mm, 0.5 mm deep, 3 mm/s, "
        "60 000 rpm, one tick per millisecond (3 µm feed steps). Each tick is one "
        "`BoneEngine.step_raw`: carve the burr's neighbourhood, then the force from the "
        f"voxels. After 0.5 mm of warm-up, {measure_mm:g} mm of groove is measured. "
        "Error: mean |F| against the converged analytic integral "
        "(`server/model/reference.py`). Ripple: std/mean of |F| over the measured ticks. "
        "Tick: wall time of carve + force, median and p99 over the measured ticks (this "
        "machine is shared: p99 carries its noise). `aligned`: the block's faces are "
        "parallel to the voxel grid; `oblique`: the grid is rotated "
        f"{OBLIQUE_EULER_XYZ_DEG} degrees (x, y, z), so every face cuts voxels at an angle.",
        "",
        "## Summary (worst over the nine cases)",
        "",
        "| grid | voxel mm | elements | max error % | max ripple % | tick p50 µs (median) "
        "| tick p99 µs (worst) | before: error % / ripple % / p50 µs / p99 µs |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        b = before.get((s.grid, s.voxel_mm, s.elements))
        was = (f"{100 * b.max_error_rel:.2f} / {100 * b.max_ripple_rel:.2f} / "
               f"{b.tick_p50_us:.0f} / {b.tick_p99_us:.0f}" if b is not None else "–")
        lines.append(f"| {s.grid} | {s.voxel_mm:g} | {s.elements} | "
                     f"{100 * s.max_error_rel:.2f} | {100 * s.max_ripple_rel:.2f} | "
                     f"{s.tick_p50_us:.0f} | {s.tick_p99_us:.0f} | {was} |")
    if before:
        lines += ["", f"Before: the baseline rows kept in accuracy.json (from {baseline_source}); "
                  "the plot draws them as the grey \"before\" curve."]
    lines += ["", f"Targets at {TARGET_VOXEL_MM:g} mm: |F| within {100 * TARGET_ERROR:g} % in "
              f"every case, ripple ≤ {100 * TARGET_RIPPLE:g} %, carve+force p50 ≤ "
              f"{TARGET_P50_US:g} µs and p99 ≤ {TARGET_P99_US:g} µs."]
    for s in default:
        met = (s.max_error_rel <= TARGET_ERROR and s.max_ripple_rel <= TARGET_RIPPLE
               and s.tick_p50_us <= TARGET_P50_US and s.tick_p99_us <= TARGET_P99_US)
        lines.append(f"Default ({s.elements} elements, {s.grid}): "
                     f"{100 * s.max_error_rel:.2f} % max error, "
                     f"{100 * s.max_ripple_rel:.2f} % max ripple, p50 {s.tick_p50_us:.0f} µs, "
                     f"p99 {s.tick_p99_us:.0f} µs — {'met' if met else 'NOT met'}.")
    lines += [
        "",
        "![tick time against error](accuracy.png)",
        "",
        "## Every case",
        "",
        "| grid | voxel mm | elements | orientation | angle ° | |F| N | reference N | error % "
        "| ripple % | p50 µs | p99 µs |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r.grid} | {r.voxel_mm:g} | {r.elements} | {r.orientation} | "
                     f"{r.angle_deg:g} | {r.force_N:.4f} | {r.reference_N:.4f} | "
                     f"{100 * r.error_rel:+.2f} | {100 * r.ripple_rel:.2f} | "
                     f"{r.tick_p50_us:.0f} | {r.tick_p99_us:.0f} |")
    lines.append("")
    return "\n".join(lines)


def pareto_front(points: list[tuple[float, float]]) -> tuple[list[float], list[float]]:
    """The lower-left envelope of (time, error) points as a step curve: for each time, the
    smallest error reached at or below it."""
    xs: list[float] = []
    ys: list[float] = []
    for x, y in sorted(points):
        if ys and y >= ys[-1]:
            continue
        if xs:
            xs.append(x)
            ys.append(ys[-1])
        xs.append(x)
        ys.append(y)
    return xs, ys


def plot(rows: list[AccuracyRow], path: Path, baseline: list[AccuracyRow] | None = None
         ) -> None:
    from ..plotting import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.8, 4.6))
    summary = summarize(rows)
    for points, style, label in (
            (summarize(baseline or []), dict(color="0.6", linestyle="--"), "before"),
            (summary, dict(color="k", linestyle="-"), "now")):
        if not points:
            continue
        xs, ys = pareto_front([(p.tick_p99_us, max(100 * p.max_error_rel, 1e-3))
                               for p in points])
        ax.loglog(xs, ys, linewidth=1.2, label=f"{label}: best error for the time", **style)
        if label == "before":
            for p in points:
                ax.loglog(p.tick_p99_us, max(100 * p.max_error_rel, 1e-3),
                          {512: "v", 1152: "o", 2048: "s"}.get(p.elements, "D"), color="0.7",
                          markerfacecolor="none", markersize=5)
    markers = {512: "v", 1152: "o", 2048: "s"}
    colours = {}
    for s in summary:
        colour = colours.setdefault(s.voxel_mm, f"C{len(colours)}")
        filled = s.grid == "aligned"
        ax.loglog(s.tick_p99_us, max(100 * s.max_error_rel, 1e-3),
                  markers.get(s.elements, "D"), color=colour,
                  markerfacecolor=colour if filled else "none", markersize=8)
    for voxel, colour in colours.items():
        ax.plot([], [], "o", color=colour, label=f"{voxel:g} mm voxels")
    for elements, marker in markers.items():
        if any(s.elements == elements for s in summary):
            ax.plot([], [], marker, color="0.4", label=f"{elements} elements")
    if any(s.grid == "oblique" for s in summary):
        ax.plot([], [], "o", color="0.4", markerfacecolor="none", label="oblique grid")
    ax.axhline(100 * TARGET_ERROR, color="r", linestyle=":", linewidth=1, label="2 % target")
    ax.axvline(TARGET_P99_US, color="r", linestyle="--", linewidth=1,
               label=f"{TARGET_P99_US:g} µs p99 target")
    ax.set_xlabel("carve + force per tick, p99 over the worst case (µs)")
    ax.set_ylabel("worst |F| error over the nine cases (%)")
    ax.set_title("Voxel engine: error against time per tick")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    save_figure(fig, path)


_voxel_size = float_in(0.02, 0.5, "voxel size", "mm")


_element_counts = comma_separated(int, lambda c: 32 <= c <= 20000, "element counts",
                                 "element count must be in 32..20000")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "accuracy", main, help="voxel engine force error, ripple and tick time",
        description="Steady grooves for the thesis's nine cases at several voxel sizes and "
                    "burr element counts: error against the analytic force, ripple, carve + "
                    "force time per tick. Writes OUT/accuracy.md, accuracy.json, "
                    "accuracy.png.", json_help=runner.JSON_ROWS)
    p.add_argument("--voxel-mm", type=_voxel_size,
                   help="only this voxel size (mm). Default 0.05, 0.1, 0.2, 0.4")
    p.add_argument("--elements", type=_element_counts,
                   help="burr element counts, comma-separated (rounded to n × 2n). "
                        f"Default {','.join(str(2 * n * n) for n in N_THETAS)}")
    p.add_argument("--measure-mm", type=float, default=3.0,
                   help="groove length measured per case after 0.5 mm warm-up. Default 3")
    p.add_argument("--no-oblique", action="store_true",
                   help="skip the runs on an oblique grid")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")
    p.add_argument("--no-edges", action="store_true",
                   help="skip the edge rows (plunges, retracing a groove, burr shapes)")
    p.add_argument("--baseline", type=Path,
                   help="accuracy.json to compare against (drawn as \"before\"). Default: the "
                        "baseline kept in OUT/accuracy.json, or that file's rows if it has none")


def main(args: argparse.Namespace) -> int:
    if not 0.1 <= args.measure_mm <= 20.0:
        raise ValueError(f"--measure-mm must be in [0.1, 20], got {args.measure_mm}")
    voxel_sizes = (args.voxel_mm,) if args.voxel_mm is not None else VOXEL_SIZES_MM
    n_thetas = N_THETAS if args.elements is None else tuple(
        max(2, round((c / 2.0) ** 0.5)) for c in args.elements)
    flags = []
    if args.voxel_mm is not None:
        flags.append(f"--voxel-mm {args.voxel_mm:g}")
    if args.elements is not None:
        flags.append("--elements " + ",".join(map(str, args.elements)))
    if args.measure_mm != 3.0:
        flags.append(f"--measure-mm {args.measure_mm:g}")
    if args.no_oblique:
        flags.append("--no-oblique")
    if args.no_edges:
        flags.append("--no-edges")
    command = " ".join(["burrforce bench accuracy", *flags])

    def progress(row: AccuracyRow) -> None:
        print(f"  {row.grid} {row.voxel_mm:g} mm {row.elements} el {row.orientation} "
              f"{row.angle_deg:g}°: error {100 * row.error_rel:+.2f} %, ripple "
              f"{100 * row.ripple_rel:.2f} %, p50 {row.tick_p50_us:.0f} µs, "
              f"p99 {row.tick_p99_us:.0f} µs", file=sys.stderr)

    out = runner.out_dir(args)
    explicit = getattr(args, "baseline", None) is not None
    baseline, baseline_source = load_baseline(
        args.baseline if explicit else out / "accuracy.json", explicit)
    rows = run(voxel_sizes, n_thetas, not args.no_oblique, args.measure_mm, progress)
    edges: list[dict] = []
    if not args.no_edges:
        edge_voxel = args.voxel_mm if args.voxel_mm is not None else TARGET_VOXEL_MM
        edges = edge_rows(edge_voxel, not args.no_oblique, lambda r: print(
            f"  {r['kind']} {r['grid']} {r['case']}: {r['value']:.4g} (target "
            f"{r['target']:g}{'' if r['ok'] else ', NOT MET'})", file=sys.stderr))
    out.mkdir(parents=True, exist_ok=True)
    markdown = render_markdown(rows, command, args.measure_mm, baseline, baseline_source)
    if edges:
        markdown += "\n".join(["", "## Edges", "", EDGES_INTRO, *render_edges(edges)]) + "\n"
    (out / "accuracy.md").write_text(markdown)
    (out / "accuracy.json").write_text(json.dumps({
        "source": f"{command} on {dt.date.today().isoformat()}",
        "rows": [asdict(r) for r in rows],
        "baseline_source": baseline_source,
        "baseline": [asdict(r) for r in baseline],
        "edges": edges,
    }, indent=1))
    if not args.no_plot:
        plot(rows, out / "accuracy.png", baseline)
    return runner.report(args, out / "accuracy.md", out / "accuracy.json",
                         *(() if args.no_plot else (out / "accuracy.png",)),
                         rows=[asdict(r) for r in rows], indent=1)
