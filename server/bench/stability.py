"""``burrforce bench stability``: a closed-loop stress harness for the haptic output.

Each run closes the haptic loop through the real protocol — the real hot-loop process, real
UDP datagrams on 127.0.0.1, the real codec and tags — around a simulated device and hand, in
**simulated time**: the client samples the device, sends its POSE, waits (up to 1 s of wall
time) for the reply, and only then advances the simulation to the next sample. Nothing is
paced in real time, so a simulated second takes a fraction of one, and a run is reproducible
from its seed whatever the machine's load.

The loop (``stability_sim``):

- **Device** (per profile, ``devices.sim``): a point mass (``sim_mass_kg`` + a 0.1 kg grip)
  with viscous friction ``sim_damping_N_s_mm``, integrated by semi-implicit Euler with at
  least 10 substeps per packet interval and none longer than 0.1 ms. The encoder quantizes each
  axis to the profile's ``resolution_mm`` (the position sent); the energy uses the true state.
  Raw replies: the device feels the last good reply's ``force`` held from that reply's
  (simulated) arrival on; an error reply means zero force; no good reply for 50 ms means zero
  force (SPEC 7.6); an older reply than one already used is ignored (SPEC 5.1). Coupled
  replies go through the device loop's renderer (``devices.render``, ``--render servo``, the
  default): every servo tick (1/``rated_hz``) it reads the encoder, estimates the velocity
  (FOAW) and renders the newest coupling model, extrapolated, delay-limited, with a passivity
  controller and a 30 ms watchdog; ``--render hold`` holds each coupled reply's ``force``
  instead, as the bench did before the device loop existed.
- **Hand**: a spring-damper (0.3 N/mm, 0.003 N·s/mm) pulling the device toward a target:
  above the block at x = 3 mm, down in 0.2 s until the burr centre is 1 mm below the top
  face (the burr's bottom 3 mm deep, so the hand presses with up to 0.9 N), then along +x
  at the feed speed to x = 23 mm, held there. The thesis's groove: workpiece phantom
  (cortical block x 0–26, y ±8, top face z = 0, 0.1 mm voxels), tool axis
  (−cos 60°, 0, sin 60°), 2 mm burr radius, shaft on.
- **Network**, in simulated time: a round-trip delay (0.3 ms base) plus up to the jitter on
  arrival, and the jitter on each sample interval (dt + U(−j, j)); loss of requests and,
  independently, of replies; duplicates (the datagram sent twice: the server drops the copy);
  reordering (a datagram held and sent after the next one: the server answers only the
  newer). Seeded per run (``run_seed``). The client says hello until the server's NEW_STREAM
  notice arrives, then streams in the stream it was given (SPEC 5.2).
- **Events**: ``teleport`` (the target jumps 30 mm up at 0.6 s and back down at 0.8 s),
  ``nan`` (a 20 ms burst of NaN poses at 0.5 s and two single ones: the server answers
  BAD_VALUE), ``inside`` (the burr starts fully embedded, centre 3 mm deep), ``inside_rigid``
  (the same at 0 rpm), ``leave_grid`` (fed at 50 mm/s past the block to x = 45 mm, outside
  the grid).

Sweeps, one factor at a time around the base case (60 000 rpm, 10 mm/s, Us × 1, K 1.3,
dt 1 ms, 0.3 ms delay, clean network), each run on a fresh session (a fresh bone), for every
profile × output mode; plus the grid Us × dt for the stability map.

Per run (``--json`` prints these rows):

- ``nonfinite``: replies with a non-finite number in any field, plus a non-finite device
  state (the run then stops). Must be 0.
- ``limit_violations``: replies whose force exceeds the profile's max force, whose force
  moved more than ``max_slew × Δt`` from the server's previous reply, or (coupled) whose
  coupling stiffness or damping exceed the profile's maxima. Checked on every reply the server
  sent, in sequence order, the way the server limits: Δt is the client-time interval since
  its last good tick, capped at the 50 ms stream gap; 1 ms on a stream's first tick; after an
  error reply the reference is zero (the server releases the device). Tolerance 1e-9
  relative + 1e-9 N (float rounding only). Must be 0.
- ``energy_generated_J``: the largest running value over the run of ∫ F_applied · v dt with
  the device's true velocity (exact per substep: the force is constant over it) — the net
  energy the server's force put into the device. A passive output starting at rest keeps it
  ≤ 0. Tolerance **1 mJ**: about ten times what sampling and quantization leak in a passive
  render here (a 1 N/mm coupling held for 1 ms at 10 mm/s for a second leaks k·T/2·∫v² ≈
  0.05 mJ), and well below a limit cycle's (a 1 N buzz over 0.1 mm at 100 Hz puts in ~0.1 mJ
  per cycle).
- ``oscillation``: the RMS of the applied force minus its 25 ms centred moving average, over
  the second half of the run (``oscillation_N``), above **5 %** of the profile's max force —
  a limit cycle or buzz faster than 40 Hz. A run's own events count: what the hand feels
  (``oscillation_tail_N``, the same over the last quarter only, tells a decaying transient
  from a sustained cycle; it does not enter the verdict).
- ``stable``: nonfinite 0, no violations, energy within tolerance, no oscillation.
- extras: mean and max applied force, the largest force sent, bone removed, deepest burr
  bottom below the top face, ticks, replies lost (in the channel or never received), error
  replies, clamped and cutting fractions, wall time, the seed and every scenario setting.

Tolerances were fixed before measuring and are not tuned per mode: the tables report what was
measured.
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import time
from pathlib import Path

from ...proto.tag import new_key
from ..haptics.profiles import PROFILES
from . import runner
from .stability_sim import RENDERS, Link, Scenario, simulate
from .timing import machine_line

MODES = ("raw", "coupled")
ENERGY_TOL_J = 1e-3
OSC_FRACTION = 0.05
VOXEL_MM = 0.1
DEFAULT_SEED = 1

BASE = Scenario("base")
#: The stability map's axes (the png): Us scale × packet interval.
GRID_US = (0.1, 1.0, 10.0, 100.0)
GRID_DT_MS = (0.1, 0.5, 2.0, 10.0, 50.0)
#: Cases in the map's plane (everything else at base).
MAP_CASES = ("base", "us", "dt", "grid")


def sweep_cases() -> list[Scenario]:
    """The full run's scenarios: one factor at a time around BASE, events, and the grid."""
    b = BASE
    cases = [b]
    cases += [b.with_(case="rpm", value=r, rpm=r) for r in (0.0, 3000.0, 10_000.0, 30_000.0,
                                                              100_000.0)]
    cases += [b.with_(case="feed", value=f, feed_mm_s=f) for f in (1.0, 50.0, 200.0, 500.0)]
    cases += [b.with_(case="us", value=u, us_scale=u) for u in (0.1, 0.3, 3.0, 10.0, 30.0,
                                                                 100.0)]
    cases += [b.with_(case="k", value=k, k=k) for k in (0.0, 3.0, 5.0)]
    cases += [b.with_(case="dt", value=d, dt_ms=d) for d in (0.1, 0.5, 2.0, 10.0, 50.0)]
    cases += [b.with_(case="delay", value=d, delay_ms=d) for d in (1.0, 5.0, 20.0)]
    cases += [b.with_(case="jitter", value=j, jitter_ms=j) for j in (0.3, 2.0)]
    cases += [b.with_(case="loss", value=p, loss=p) for p in (0.05, 0.3)]
    cases += [b.with_(case="duplicate", value=0.2, duplicate=0.2),
              b.with_(case="reorder", value=0.2, reorder=0.2),
              b.with_(case="wifi", value=None, delay_ms=5.0, jitter_ms=2.0, loss=0.05,
                      duplicate=0.02, reorder=0.05)]
    cases += [b.with_(case="teleport", event="teleport"),
              b.with_(case="nan", event="nan"),
              b.with_(case="inside", event="inside"),
              b.with_(case="inside_rigid", value=0.0, event="inside", rpm=0.0),
              b.with_(case="leave_grid", event="leave_grid")]
    on_axis = {(c.us_scale, c.dt_ms) for c in cases if c.case in MAP_CASES}
    cases += [b.with_(case="grid", value=u, us_scale=u, dt_ms=d)
              for u in GRID_US for d in GRID_DT_MS if (u, d) not in on_axis]
    return cases


def quick_cases() -> list[Scenario]:
    """A representative subset: the base, a stiff bone, a slow link, a bad network with NaN
    poses, rigid contact from inside the bone."""
    b = BASE
    return [b,
            b.with_(case="us", value=100.0, us_scale=100.0),
            b.with_(case="dt", value=10.0, dt_ms=10.0),
            b.with_(case="wifi_nan", value=None, delay_ms=5.0, jitter_ms=2.0, loss=0.05,
                    duplicate=0.02, reorder=0.05, event="nan"),
            b.with_(case="inside_rigid", value=0.0, event="inside", rpm=0.0)]


def run(profiles: list[str], cases: list[Scenario], seed: int = DEFAULT_SEED,
        modes: tuple[str, ...] = MODES, progress=None, render: str = "servo") -> list[dict]:
    """Every profile × mode × case, each on a fresh session of one hot-loop process;
    ``render`` says how coupled replies reach the device (``stability_sim.RENDERS``)."""
    from ..bone.materials import CORTICAL, CORTICAL_LABEL, Material, MaterialTable
    from ..haptics import HapticsConfig
    from ..hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec

    say = progress or (lambda text: None)
    key = new_key()
    hot = HotLoopProcess(HotLoopConfig())
    rows: list[dict] = []
    say("starting the hot loop (warm-up compiles or loads the kernels)")
    address = hot.start()
    link = Link(address, key)
    gc.collect()
    gc.freeze()
    session_id = 100
    total = len(profiles) * len(modes) * len(cases)
    try:
        for name in profiles:
            profile = PROFILES[name]
            for mode in modes:
                haptics = HapticsConfig.for_device(profile, mode)
                for sc in cases:
                    session_id += 1
                    material = Material(CORTICAL.name, CORTICAL.us_n_mm2 * sc.us_scale, sc.k)
                    spec = SessionSpec(session_id, "phantom:workpiece", VOXEL_MM, key,
                                       SessionConfig(haptics=haptics),
                                       materials=MaterialTable({CORTICAL_LABEL: material}),
                                       publish=False)
                    hot.call("add_session", spec=spec)
                    try:
                        row = simulate(link, session_id, profile, mode, sc, seed,
                                       ENERGY_TOL_J, OSC_FRACTION, render=render)
                    finally:
                        hot.call("remove_session", session_id=session_id)
                    rows.append(row)
                    say(f"[{len(rows)}/{total}] {_label(row)}: "
                        f"{'stable' if row['stable'] else 'UNSTABLE'} "
                        f"(E {row['energy_generated_J'] * 1e3:+.3f} mJ, osc "
                        f"{row['oscillation_N']:.3f} N, viol {row['limit_violations']}, "
                        f"nonfinite {row['nonfinite']}, {row['wall_s']:.1f} s)")
        if not hot.is_alive():
            raise RuntimeError("the hot-loop process died during the run")
    finally:
        link.close()
        hot.stop()
    return rows


def _label(row: dict) -> str:
    value = "" if row["value"] is None else f"={row['value']:g}"
    extra = f" dt={row['sc_dt_ms']:g}" if row["case"] == "grid" else ""
    return f"{row['profile']}/{row['mode']}/{row['case']}{value}{extra}"


def summarize(rows: list[dict]) -> list[dict]:
    """Per profile × mode: runs, nonfinite, violations, max energy, oscillating, unstable."""
    out = []
    keys = sorted({(r["profile"], r["mode"]) for r in rows},
                  key=lambda k: (list(PROFILES).index(k[0]), MODES.index(k[1])))
    for profile, mode in keys:
        rs = [r for r in rows if r["profile"] == profile and r["mode"] == mode]
        out.append({
            "profile": profile, "mode": mode, "runs": len(rs),
            "nonfinite": sum(r["nonfinite"] for r in rs),
            "limit_violations": sum(r["limit_violations"] for r in rs),
            "max_energy_generated_J": max(r["energy_generated_J"] for r in rs),
            "oscillating_runs": sum(r["oscillation"] for r in rs),
            "unstable_runs": sum(not r["stable"] for r in rs),
            "unstable_cases": [_label(r).split("/", 2)[2] for r in rs if not r["stable"]],
        })
    return out


def _fmt(x: object) -> str:
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        return f"{x:.4g}"
    return "" if x is None else str(x)


def summary_table(summary: list[dict]) -> list[str]:
    lines = ["| profile | mode | runs | nonfinite | violations | max energy generated mJ | "
             "oscillating runs | unstable runs |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for s in summary:
        lines.append(f"| {s['profile']} | {s['mode']} | {s['runs']} | {s['nonfinite']} | "
                     f"{s['limit_violations']} | {s['max_energy_generated_J'] * 1e3:.3f} | "
                     f"{s['oscillating_runs']} | {s['unstable_runs']} |")
    return lines


ROW_COLUMNS = (("profile", "profile"), ("mode", "mode"), ("case", "case"), ("value", "value"),
               ("sc_dt_ms", "dt ms"), ("nonfinite", "nonfinite"),
               ("limit_violations", "violations"), ("energy_generated_J", "energy J"),
               ("oscillation", "osc"), ("oscillation_N", "osc N"),
               ("oscillation_tail_N", "osc tail N"), ("stable", "stable"),
               ("mean_force_N", "mean F N"), ("max_force_N", "max F N"),
               ("removed_mm3", "removed mm³"), ("max_depth_mm", "depth mm"),
               ("ticks", "ticks"), ("replies_lost", "lost"),
               ("clamped_fraction", "clamped"), ("wall_s", "wall s"))


def write_results(rows: list[dict], settings: dict, out: Path) -> tuple[Path, Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y-%m-%d %H:%M")
    summary = summarize(rows)
    result = {"date": stamp, "machine": machine_line(), "settings": settings,
              "summary": summary, "rows": rows}
    json_path = out / "stability.json"
    json_path.write_text(json.dumps(result, indent=2) + "\n")
    png_path = out / "stability.png"
    plot_map(rows, png_path)
    lines = [
        "# Closed-loop stability (`burrforce bench stability`)",
        "",
        f"{stamp}; {machine_line()}. {len(rows)} runs in {settings['wall_s']:.0f} s "
        f"(seed {settings['seed']}; coupled replies rendered by "
        f"`{settings.get('render', 'hold')}`). Real hot loop, real UDP and codec; simulated "
        "device, hand and network in simulated time (method and tolerances: the module "
        "docstring of `server/bench/stability.py`). Each run: the thesis's groove on the workpiece "
        f"phantom ({VOXEL_MM:g} mm voxels), a fresh session, "
        f"{BASE.duration_s:g} s simulated. Stable = no non-finite value, no limit violation, "
        f"energy generated ≤ {ENERGY_TOL_J * 1e3:g} mJ, oscillation RMS ≤ "
        f"{OSC_FRACTION * 100:g} % of the profile's max force.",
        "",
        "## Summary",
        "",
        *summary_table(summary),
        "",
        "Unstable runs per profile × mode:",
        "",
    ]
    for s in summary:
        cases = ", ".join(s["unstable_cases"]) or "none"
        lines.append(f"- {s['profile']} / {s['mode']}: {cases}")
    lines += ["", f"Stability map (Us scale × packet interval): `{png_path.name}`.", "",
              "## Every run", "",
              "| " + " | ".join(h for _, h in ROW_COLUMNS) + " |",
              "|" + "---|" * len(ROW_COLUMNS)]
    for r in rows:
        cells = [_fmt(r[k]) for k, _ in ROW_COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return runner.write_page(out, "stability", lines), json_path, png_path


def plot_map(rows: list[dict], path: Path) -> None:
    """Per profile: stable (filled circle) or not (cross) over Us scale × dt, raw on the left
    of each grid point, coupled on the right."""
    from ..plotting import pyplot, save_figure

    plt = pyplot()
    profiles = [p for p in PROFILES if any(r["profile"] == p for r in rows)]
    n = max(1, len(profiles))
    cols = 2 if n > 1 else 1
    nrows = (n + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(6.0 * cols, 5.0 * nrows), squeeze=False)
    shift = {"raw": 0.88, "coupled": 1.12}
    color = {"raw": "tab:orange", "coupled": "tab:blue"}
    for ax, profile in zip(axes.flat, profiles, strict=False):
        for mode in MODES:
            pts = [r for r in rows if r["profile"] == profile and r["mode"] == mode
                   and r["case"] in MAP_CASES]
            ok = [(r["sc_us_scale"] * shift[mode], r["sc_dt_ms"]) for r in pts if r["stable"]]
            bad = [(r["sc_us_scale"] * shift[mode], r["sc_dt_ms"]) for r in pts
                   if not r["stable"]]
            if ok:
                ax.scatter(*zip(*ok, strict=True), marker="o", s=60, color=color[mode],
                           label=f"{mode}: stable")
            if bad:
                ax.scatter(*zip(*bad, strict=True), marker="x", s=60, color=color[mode],
                           linewidths=2, label=f"{mode}: unstable")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(0.05, 200)
        ax.set_ylim(0.07, 80)
        ax.set_xlabel("Us scale (× 805.1 N/mm²)")
        ax.set_ylabel("packet interval dt, ms")
        ax.set_title(f"{profile}")
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=4)
    for ax in list(axes.flat)[len(profiles):]:
        ax.axis("off")
    fig.suptitle("Stable operating region: raw (left of each point) vs coupled (right)")
    fig.tight_layout()
    save_figure(fig, path)


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = runner.add_bench(
        sub, "stability", main,
        help="closed-loop stability of the haptic output (simulated device)",
        description="A 1 kHz closed loop through the real protocol and hot loop, with a "
                    "simulated device, hand and network in simulated time: sweeps of rpm, "
                    "feed, Us, K, packet interval, network impairments and events, per "
                    "device profile and output mode. The full run writes OUT/stability.md, "
                    "stability.json and stability.png; --quick only prints.",
        json_help=runner.JSON_ROWS)
    p.add_argument("--quick", action="store_true",
                   help="a representative subset (all profiles, both modes, 5 cases); "
                        "prints, writes no files")
    p.add_argument("--profiles", nargs="+", choices=list(PROFILES), default=list(PROFILES),
                   metavar="PROFILE", help=f"device profiles (default all: "
                                           f"{', '.join(PROFILES)})")
    p.add_argument("--cases", nargs="+", metavar="CASE",
                   help="only the runs of these cases (e.g. base teleport inside "
                        "inside_rigid); default every case")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES),
                   help="output modes. Default both")
    p.add_argument("--seed", type=int, default=DEFAULT_SEED,
                   help=f"network/jitter seed. Default {DEFAULT_SEED}")
    p.add_argument("--render", choices=RENDERS, default="servo",
                   help="how the device renders coupled replies: servo = the device loop's "
                        "servo-rate re-rendering of the coupling model (devices.render), hold "
                        "= each reply's force held until the next (the behaviour before the "
                        "device loop). Default servo")


def main(args: argparse.Namespace) -> int:
    say = runner.say
    cases = quick_cases() if args.quick else sweep_cases()
    if args.cases:
        unknown = set(args.cases) - {c.case for c in cases}
        if unknown:
            say(f"unknown case(s): {', '.join(sorted(unknown))}")
            return 2
        cases = [c for c in cases if c.case in args.cases]
    t0 = time.perf_counter()
    rows = run(args.profiles, cases, args.seed, modes=tuple(args.modes), progress=say,
               render=args.render)
    wall = time.perf_counter() - t0
    if not args.quick:
        settings = {"seed": args.seed, "render": args.render, "wall_s": wall,
                    "cases": args.cases, "modes": args.modes,
                    "energy_tol_J": ENERGY_TOL_J,
                    "oscillation_fraction": OSC_FRACTION, "voxel_mm": VOXEL_MM,
                    "profiles": args.profiles}
        md, js, png = write_results(rows, settings, runner.out_dir(args))
        say(f"results written to {md}, {js} and {png}")
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        print("\n".join(summary_table(summarize(rows))))
    say(f"{len(rows)} runs in {wall:.1f} s")
    return 0
