"""Instruction count per bone tick on the accuracy groove, repeatable on a busy machine.

``python -m benchmarks.tick_profile`` ploughs one of ``bench accuracy``'s grooves
and reports the callgrind instruction count (Ir) per tick: it runs itself under
``valgrind --tool=callgrind --instr-atstart=no`` and switches instrumentation on only around
the measured ticks (client requests through a tiny C helper built with the system's cc and
``valgrind/callgrind.h``), so start-up, imports and warm-up cost neither time nor counts.
``--part carve`` counts only the carving kernel (the force stage is then tick − carve).
``--burr NAME`` ploughs the same groove with another burr, its lowest point as deep: a 6-flute
round burr of the same radius (``round-fluted``) or ``bench accuracy``'s shapes (``BURRS``);
each runs the one tick (``bone.tick.bone_tick``) with the revolved-profile hooks
(``bone.tick_tables.RevolvedTick``: every burr but the round abrasive one).
``--no-callgrind`` prints wall-time percentiles instead (indicative only on a shared machine).

Examples::

    .venv/bin/python -m benchmarks.tick_profile --grid aligned
    .venv/bin/python -m benchmarks.tick_profile --grid oblique --part carve
"""

from __future__ import annotations

import argparse
import ctypes
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

from burrforce.server import compile_cache

# Run as ``python -m``, not through the ``burrforce`` command: point numba at the cache of
# these sources before it is imported (its cache keys a kernel on its own file only, so the
# shared default cache can hold a tick compiled from other sources).
compile_cache.configure()

from burrforce.server.bench.groove import (  # noqa: E402
    GROOVE_BLOCK_HI_MM,
    GROOVE_BLOCK_LO_MM,
    groove_block,
    oblique_rotation,
)
from burrforce.server.bench.shapes import BURRS, centre_at_depth  # noqa: E402
from burrforce.server.bone import BoneEngine, ShaftParams  # noqa: E402
from burrforce.server.bone.carve import carve_sphere  # noqa: E402
from burrforce.server.model import thesis_cases  # noqa: E402
from burrforce.server.model.shapes import Burr, Fluted, Sphere  # noqa: E402

from . import child_env  # noqa: E402

#: ``--burr`` choices: the round abrasive burr (the engine's own, radius 2 mm), the same sphere
#: with 6 flutes, and the shapes ``bench accuracy`` checks against their references.
BURR_CHOICES = {"round": None, "round-fluted": Burr(Sphere(2.0), Fluted(n_flutes=6))} | {
    name: burr for name, burr in BURRS.items() if name != "sphere"}

_HELPER_C = """
#include <valgrind/callgrind.h>
void start(void) { CALLGRIND_START_INSTRUMENTATION; }
void stop(void) { CALLGRIND_STOP_INSTRUMENTATION; }
"""


def _callgrind_helper(tmp: str) -> ctypes.CDLL:
    """Build and load the start/stop helper (client requests are no-ops outside valgrind)."""
    src = os.path.join(tmp, "cg_helper.c")
    lib = os.path.join(tmp, "cg_helper.so")
    with open(src, "w") as f:
        f.write(_HELPER_C)
    subprocess.run(["cc", "-O1", "-shared", "-fPIC", "-o", lib, src], check=True)
    return ctypes.CDLL(lib)


def _ticks(args: argparse.Namespace, measured: int, helper: ctypes.CDLL | None = None
           ) -> list[int]:
    """Run warm-up + ``measured`` ticks in this process; returns each measured tick's ns."""
    case = next(c for c in thesis_cases()
                if c.orientation == args.orientation and c.angle_deg == args.angle)
    direction = oblique_rotation() if args.grid == "oblique" else None
    grid = groove_block(args.voxel_mm, direction)
    n_theta = max(2, round((args.elements / 2.0) ** 0.5))
    engine = BoneEngine(grid, shaft=ShaftParams(length_mm=0.0), n_theta=n_theta)
    burr = BURR_CHOICES[args.burr]
    centre = case.centre_mm  # the thesis's: the round burr's lowest point at its depth
    if burr is not None:
        engine.set_burr(burr)
        if not isinstance(burr.shape, Sphere):
            axis = case.axis / np.linalg.norm(case.axis)
            centre = centre_at_depth(burr.shape, axis, case.depth_mm)
    engine.warm_up()
    velocity = case.feed_velocity_mm_s
    feed_dir = case.feed_direction / np.linalg.norm(case.feed_direction)
    mid = 0.5 * (np.asarray(GROOVE_BLOCK_LO_MM) + np.asarray(GROOVE_BLOCK_HI_MM))
    total_mm = 0.5 + args.ticks * case.feed_mm_s * 1e-3
    start = np.array([mid[0], mid[1], 0.0]) - 0.5 * total_mm * feed_dir + centre
    axis_g = grid.to_grid_vector(case.axis / np.linalg.norm(case.axis))
    feed_g = grid.to_grid_vector(velocity)
    warm = round(0.5 / (case.feed_mm_s * 1e-3))
    g = engine.grid
    carve_only = args.part == "carve"
    if carve_only and burr is not None:
        raise SystemExit("--part carve times the round abrasive burr's carve only")
    if carve_only:  # compile outside the measurement
        far = np.full(3, -1e5)
        carve_sphere(g.density, g.swept, g.labels, engine.materials.forbidden, g.brick_bone,
                     g.brick_full, g.brick_version, engine._brick_forbidden, g.spacing_mm, far,
                     engine._previous, engine.params.radius_mm, True, g.version + 1,
                     engine._removed_tick, engine.touch, engine._touched, engine._cache, 1)
    times = []
    clock = time.perf_counter_ns
    for i in range(warm + measured):
        if i == warm and helper is not None:
            helper.start()
        centre_g = grid.to_grid_point(start + velocity * (i * 1e-3))
        t0 = clock()
        if carve_only and i >= warm:
            engine._stamp += 1
            carve_sphere(g.density, g.swept, g.labels, engine.materials.forbidden,
                         g.brick_bone, g.brick_full, g.brick_version, engine._brick_forbidden,
                         g.spacing_mm, centre_g, engine._previous, engine.params.radius_mm,
                         True, g.version + 1, engine._removed_tick, engine.touch,
                         engine._touched, engine._cache, engine._stamp)
            engine._previous[:] = centre_g
        else:
            engine.step_raw(centre_g, axis_g, feed_g, case.rpm)
        if i >= warm:
            times.append(clock() - t0)
    if helper is not None:
        helper.stop()
    return times


def _callgrind_ir(argv: list[str]) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "cg.out")
        cmd = ["valgrind", "--tool=callgrind", "--instr-atstart=no",
               f"--callgrind-out-file={out}", sys.executable, "-m",
               "benchmarks.tick_profile", *argv, "--child", tmp]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                       env=child_env())
        with open(out) as f:
            text = f.read()
    m = re.search(r"^totals:\s+(\d+)", text, re.M)
    if m is None:
        raise RuntimeError("no callgrind summary line")
    return int(m.group(1))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tick_profile",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("--voxel-mm", type=float, default=0.1)
    p.add_argument("--elements", type=int, default=1152)
    p.add_argument("--grid", choices=("aligned", "oblique"), default="aligned")
    p.add_argument("--orientation", choices=("parallel", "perpendicular", "diagonal"),
                   default="parallel")
    p.add_argument("--angle", type=float, default=60.0, help="burr angle, degrees")
    p.add_argument("--ticks", type=int, default=200, help="measured ticks. Default 200")
    p.add_argument("--part", choices=("tick", "carve"), default="tick")
    p.add_argument("--burr", choices=tuple(BURR_CHOICES), default="round",
                   help="round (default: the round abrasive burr, R 2 mm), round-fluted (the "
                        "same with 6 flutes) or one of bench accuracy's shapes")
    p.add_argument("--no-callgrind", action="store_true",
                   help="wall time per tick instead of instruction counts")
    p.add_argument("--child", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child is not None:
        _ticks(args, args.ticks, _callgrind_helper(args.child))
        return 0
    label = (f"{args.grid} {args.voxel_mm:g} mm {args.elements} el {args.orientation} "
             f"{args.angle:g}° {args.burr} {args.part}")
    if args.no_callgrind:
        ns = np.asarray(_ticks(args, args.ticks)) / 1e3
        print(f"{label}: p50 {np.median(ns):.1f} µs, p99 {np.percentile(ns, 99):.1f} µs "
              f"over {args.ticks} ticks (wall, indicative)")
        return 0
    child = [a for a in (argv if argv is not None else sys.argv[1:])]
    total = _callgrind_ir(child)
    print(f"{label}: {total / args.ticks:,.0f} Ir per tick "
          f"(callgrind, {args.ticks} ticks)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
