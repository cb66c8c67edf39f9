"""Going back over a groove: the rows ``bench accuracy`` reports for retracing, reversing,
re-entering and widening a groove on the 0.1 mm workpiece block (and the strokes the tests
drive). Nothing is left to remove in the first three, so the spindle power and the force
should be ~0 (target ≤ 1 % of the first pass's); widening cuts fresh bone beside the groove,
so the spindle's energy should equal Us × the volume it removed."""

from __future__ import annotations

import numpy as np

from ..bone import BoneEngine, ShaftParams
from .groove import groove_block, oblique_rotation

RPM = 60000.0
UP = (0.0, 0.0, 1.0)
#: The groove: 0.5 mm deep with the thesis's 4 mm burr, from x = 3 to 9 mm at 10 mm/s.
DEPTH_MM = 0.5
CENTRE_Z_MM = 2.0 - DEPTH_MM
#: Ghost power and force allowed where nothing is left to cut, share of the first pass's.
TARGET_GHOST = 0.01
#: Widening: |∫P dt / (Us × removed) − 1| at most this.
TARGET_WIDEN_BALANCE = 0.03


def stroke(engine: BoneEngine, start, stop, speed_mm_s: float = 10.0, rpm: float = RPM,
           carve: bool = True) -> dict:
    """Move the burr (axis +z) from ``start`` to ``stop`` (mm) at 1 kHz. Returns the middle
    60 % of the stroke's mean power (W) and force (N), the spindle's energy (J), the removed
    bone's Us × volume (J) and the volume (mm³)."""
    start = np.asarray(start, dtype=float)
    delta = np.asarray(stop, dtype=float) - start
    n = max(1, round(float(np.linalg.norm(delta)) / (speed_mm_s * 1e-3)))
    feed = delta / np.linalg.norm(delta) * speed_mm_s
    us = float(engine.materials.us[1])
    power, force, removed = [], [], 0.0
    for i in range(n + 1):
        result = engine.step(start + delta * i / n, UP, feed, rpm, carve=carve)
        power.append(result.cut.power_W)
        force.append(result.cut.force_magnitude_N)
        removed += result.removed_mm3
    power_w, force_n = np.array(power), np.array(force)
    middle = slice(len(power_w) // 5, len(power_w) * 4 // 5)
    return {"power_W": float(power_w[middle].mean()), "force_N": float(force_n[middle].mean()),
            "spindle_J": float(power_w.sum() * 1e-3), "removal_J": us * removed * 1e-3,
            "removed_mm3": removed}


def groove_passes(engine: BoneEngine) -> dict[str, dict]:
    """The first pass, then reverse, retrace, lift out and re-enter, then widen 1 mm aside
    (entering from outside the block), each a ``stroke``'s numbers."""
    z = CENTRE_Z_MM
    passes = {"first": stroke(engine, (3.0, 6.0, z), (9.0, 6.0, z))}
    passes["reverse"] = stroke(engine, (9.0, 6.0, z), (3.0, 6.0, z))
    passes["retrace"] = stroke(engine, (3.0, 6.0, z), (9.0, 6.0, z))
    stroke(engine, (9.0, 6.0, z), (6.0, 6.0, z + 3.0), rpm=0.0)  # lift out, spindle off
    passes["descend"] = stroke(engine, (6.0, 6.0, z + 3.0), (6.0, 6.0, z), speed_mm_s=5.0)
    passes["reenter"] = stroke(engine, (6.0, 6.0, z), (8.5, 6.0, z))
    passes["widen"] = stroke(engine, (-3.0, 7.0, z), (10.0, 7.0, z))
    return passes


def retrace_rows(voxel_mm: float = 0.1, grids: tuple[str, ...] = ("aligned", "oblique"),
                 ) -> list[dict]:
    """``bench accuracy``'s retrace rows: per grid, ghost power and force of each pass over
    the cut groove (share of the first pass's) and the widening pass's energy balance."""

    rows = []
    for grid in grids:
        engine = BoneEngine(groove_block(voxel_mm, oblique_rotation() if grid == "oblique"
                                         else None), shaft=ShaftParams(length_mm=0.0))
        passes = groove_passes(engine)
        first = passes["first"]
        for name in ("reverse", "retrace", "descend", "reenter"):
            p = passes[name]
            worst = max(p["power_W"] / first["power_W"], p["force_N"] / first["force_N"])
            rows.append({"kind": "retrace", "grid": grid, "voxel_mm": voxel_mm, "case": name,
                         "metric": "power and force, share of the first pass's (worse of)",
                         "value": worst, "target": TARGET_GHOST,
                         "ok": bool(worst <= TARGET_GHOST)})
        w = passes["widen"]
        balance = w["spindle_J"] / w["removal_J"] - 1.0
        rows.append({"kind": "retrace", "grid": grid, "voxel_mm": voxel_mm, "case": "widen",
                     "metric": "∫P dt / (Us × removed) − 1", "value": balance,
                     "target": TARGET_WIDEN_BALANCE,
                     "ok": bool(abs(balance) <= TARGET_WIDEN_BALANCE)})
    return rows
