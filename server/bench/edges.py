"""The edges ``bench accuracy`` reports beside the steady grooves: plunges along the tool
axis, going back over a groove, and each burr shape against its own reference. Each row is a
dict: kind, grid, voxel_mm, case, metric, value, target, ok."""

from __future__ import annotations

from collections.abc import Callable

from .plunge import plunge_rows
from .retrace import retrace_rows
from .shapes import shape_rows


def edge_rows(voxel_mm: float = 0.1, oblique: bool = True,
              progress: Callable[[dict], None] | None = None) -> list[dict]:
    """Plunge, retrace and shape rows at ``voxel_mm`` (aligned grid, and oblique unless
    ``oblique`` is False)."""
    grids = ("aligned", "oblique") if oblique else ("aligned",)
    rows: list[dict] = []
    for make in (lambda: _plunge_edges(plunge_rows(voxel_mm=voxel_mm), grids),
                 lambda: retrace_rows(voxel_mm, grids), shape_rows):
        for row in make():
            rows.append(row)
            if progress is not None:
                progress(row)
    return rows


#: Plunge removal against the analytic cap, from this depth on (mm), within TARGET_REMOVAL.
REMOVAL_FROM_MM = 0.01
TARGET_REMOVAL = 0.02


def _plunge_edges(plunges: list[dict], grids: tuple[str, ...]) -> list[dict]:
    """``plunge.plunge_rows`` as edge rows: per model, grid and tool angle, the worst removal
    error from 10 µm deep, and the falling steps of force and removal on the fine sweep."""
    rows = []
    for p in plunges:
        if p["model"] == "voxel" and p["grid"] not in grids:
            continue
        grid = "flat model" if p["model"] == "flat" else p["grid"]
        case = f"{p['angle_deg']:g}° to the surface"
        deep = {d: e for d, e in p["removal_error_rel"].items() if d >= REMOVAL_FROM_MM}
        worst_depth = max(deep, key=lambda d: abs(deep[d]))
        error = deep[worst_depth]
        rows.append({"kind": "plunge", "grid": grid, "voxel_mm": p["voxel_mm"], "case": case,
                     "metric": f"removal vs the analytic cap, worst from "
                               f"{REMOVAL_FROM_MM * 1e3:g} µm (at {worst_depth * 1e3:g} µm)",
                     "value": error, "target": TARGET_REMOVAL,
                     "ok": bool(abs(error) <= TARGET_REMOVAL)})
        falls = p["normal_decreases"] + p["removal_decreases"]
        worst = 100 * min(p["worst_normal_step_rel"], p["worst_removal_step_rel"])
        rows.append({"kind": "plunge", "grid": grid, "voxel_mm": p["voxel_mm"], "case": case,
                     "metric": f"falling steps of force and removal, {p['steps']}-depth sweep "
                               f"(worst {worst:.3g} %)",
                     "value": float(falls), "target": 0.0, "ok": falls == 0})
    return rows


def _value(row: dict) -> str:
    v = row["value"]
    return f"{v:.3g}" if abs(v) < 1e-3 or abs(v) >= 10 else f"{v:.4f}"


def render_edges(rows: list[dict]) -> list[str]:
    """Markdown lines: one table per kind, a verdict per row."""
    titles = {"plunge": "Plunges along the tool axis (the spin pole on the bone)",
              "retrace": "Going back over a groove (the burr's own path)",
              "shape": "Burr shapes against their own converged references"}
    lines: list[str] = []
    for kind, title in titles.items():
        mine = [r for r in rows if r["kind"] == kind]
        if not mine:
            continue
        lines += ["", f"### {title}", "",
                  "| grid | voxel mm | case | metric | value | target | met |",
                  "|---|---|---|---|---:|---:|---|"]
        for r in mine:
            voxel = "–" if r.get("voxel_mm") is None else f"{r['voxel_mm']:g}"
            lines.append(f"| {r['grid']} | {voxel} | {r['case']} | {r['metric']} | "
                         f"{_value(r)} | {r['target']:g} | {'yes' if r['ok'] else 'NO'} |")
    return lines
