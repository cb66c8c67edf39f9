"""The ``burrforce`` command."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from .. import __version__, compile_cache
from ..argtypes import comma_separated, float_at_least, int_in

_positive_float = float_at_least(0.0, inclusive=False)
_non_negative_float = float_at_least(0.0, inclusive=True)
_elements = int_in(8, 1_000_000, "element count")
_angles = comma_separated(float, lambda deg: 0.0 < deg <= 90.0, "angles",
                          "angle must be in (0, 90] degrees", unit="degrees")


def _add_experiment(sub: argparse._SubParsersAction) -> None:
    from ..model.burr import DEFAULT_N_THETA
    from ..model.cases import THESIS_DEPTH_MM, THESIS_FEED_MM_S, THESIS_RPM
    from ..model.params import THESIS_K, THESIS_US_N_MM2, CuttingParams

    p = sub.add_parser(
        "experiment",
        help="the thesis's Table 1 (3 orientations × 3 angles) through the model",
        description="Run the thesis's cutting experiment through the force model: bone in "
                    "z < 0, burr centre at z = R − depth, tool axis (−cos α, 0, sin α), feed "
                    "along x (parallel), y (perpendicular) or (x+y)/√2 (diagonal).",
    )
    p.add_argument("--radius-mm", type=_positive_float, default=2.0,
                   help="burr radius R in mm (a '4 mm burr' is a diameter: R = 2). Default 2")
    p.add_argument("--depth-mm", type=_positive_float, default=THESIS_DEPTH_MM,
                   help=f"depth of cut h in mm. Default {THESIS_DEPTH_MM:g}")
    p.add_argument("--feed-mm-s", type=_positive_float, default=THESIS_FEED_MM_S,
                   help=f"feed speed in mm/s. Default {THESIS_FEED_MM_S:g}")
    p.add_argument("--rpm", type=_positive_float, default=THESIS_RPM,
                   help=f"spindle speed in rpm. Default {THESIS_RPM:g}")
    p.add_argument("--us", type=_non_negative_float, default=THESIS_US_N_MM2,
                   help=f"specific cutting energy Us in N/mm². Default {THESIS_US_N_MM2:g}")
    p.add_argument("--k", type=_non_negative_float, default=THESIS_K,
                   help=f"normal/tangential force ratio K. Default {THESIS_K:g}")
    p.add_argument("--spin", choices=("forward", "reverse"), default="forward",
                   help="forward = clockwise seen from the handle. Default forward")
    min_rpm = CuttingParams.min_cutting_rpm
    p.add_argument("--min-cutting-rpm", type=_positive_float, default=min_rpm,
                   help="below this spindle speed the burr touches instead of cutting. "
                        f"Default {min_rpm:g}")
    p.add_argument("--angles", type=_angles, default=[30.0, 60.0, 90.0],
                   help="cutting angles in degrees, comma-separated. Default 30,60,90")
    p.add_argument("--elements", type=_elements, default=2 * DEFAULT_N_THETA ** 2,
                   help="burr surface elements (latitude × longitude, rounded to "
                        f"n × 2n). Default {2 * DEFAULT_N_THETA ** 2}")
    p.add_argument("--json", action="store_true",
                   help="print a JSON list of rows instead of the table")
    p.add_argument("--plot", type=Path, metavar="PATH",
                   help="also write a PNG of the components against angle (needs matplotlib)")
    p.set_defaults(func=_run_experiment)


def _run_experiment(args: argparse.Namespace) -> int:
    from ..experiment import format_table, plot_experiment, rows_to_json, run_experiment
    from ..model import BurrGrid, CuttingModel, CuttingParams

    if args.depth_mm > 2.0 * args.radius_mm:
        raise ValueError(f"--depth-mm {args.depth_mm} exceeds the burr diameter "
                         f"{2.0 * args.radius_mm} mm")
    if args.plot is not None:  # fail before the work, not after it
        try:
            args.plot.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OSError(f"cannot write the plot to {args.plot}: {exc.strerror}") from None
        if not os.access(args.plot.parent, os.W_OK):
            raise OSError(f"cannot write the plot to {args.plot}: "
                          f"{args.plot.parent} is not writable")
    params = CuttingParams(us_n_mm2=args.us, k=args.k, radius_mm=args.radius_mm,
                           spin=args.spin, min_cutting_rpm=args.min_cutting_rpm)
    grid = BurrGrid.from_element_count(args.elements)
    model = CuttingModel(params, n_theta=grid.n_theta, n_phi=grid.n_phi)
    if not model.is_cutting_speed(args.rpm):
        print(f"warning: {args.rpm:g} rpm is below the minimum cutting speed "
              f"{args.min_cutting_rpm:g} rpm: the burr touches but does not cut, so every "
              "force is zero", file=sys.stderr)
    rows = run_experiment(model, args.angles, args.depth_mm, args.feed_mm_s, args.rpm)
    if args.json:
        print(rows_to_json(rows))
    else:
        print(f"burr R = {args.radius_mm:g} mm, depth {args.depth_mm:g} mm, feed "
              f"{args.feed_mm_s:g} mm/s, {args.rpm:g} rpm {args.spin}, Us = {args.us:g} N/mm², "
              f"K = {args.k:g}, {grid.n_elements} elements")
        print(format_table(rows))
    if args.plot is not None:
        path = plot_experiment(model, rows, args.plot, args.depth_mm, args.feed_mm_s, args.rpm)
        print(f"plot written to {path}", file=sys.stderr)
    return 0


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks of this machine that write results files",
                       description="Benchmarks a user runs on their own machine and "
                                   "hardware. Each writes its results where --out says, by "
                                   "default into a new folder "
                                   "./burrforce-bench-NAME-YYYYmmdd-HHMMSS.")
    bench_sub = p.add_subparsers(dest="bench", metavar="BENCH", required=True)
    from ..bench import accuracy as bench_accuracy
    from ..bench import device as bench_device
    from ..bench import flood as bench_flood
    from ..bench import latency as bench_latency
    from ..bench import load as bench_load
    from ..bench import load_while_streaming as bench_load_while_streaming
    from ..bench import mesh as bench_mesh
    from ..bench import model as bench_model
    from ..bench import sessions as bench_sessions
    from ..bench import soak as bench_soak
    from ..bench import stability as bench_stability
    from ..bench import startup as bench_startup

    for bench in (bench_model, bench_accuracy, bench_load, bench_load_while_streaming,
                  bench_latency, bench_stability, bench_device, bench_mesh, bench_flood,
                  bench_soak, bench_sessions, bench_startup):  # the order BENCH lists them
        bench.add_parser(bench_sub)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``burrforce`` parser; with ``command`` (one of :data:`COMMANDS`), that command's
    alone: its modules only are imported (``serve`` starts its hot loops ~0.7 s sooner
    without the other commands' numba and bone imports), and its help and errors read the
    same."""
    parser = argparse.ArgumentParser(
        prog="burrforce",
        description="Haptic force server for virtual-reality bone burring.",
    )
    parser.add_argument("--version", action="version", version=f"burrforce {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS if command is None else (command,):
        _command_parser(name)(sub)
    return parser


#: The commands, in the order COMMAND lists them.
COMMANDS = ("experiment", "calibrate", "bone", "serve", "compile", "client", "device", "bench",
            "replay", "report")


def _command_parser(name: str) -> Callable[[argparse._SubParsersAction], None]:
    """The function adding command ``name``'s parser. Its module is imported here, not at the
    top: ``main`` configures numba's cache before any of them loads it."""
    if name == "experiment":
        return _add_experiment
    if name == "bench":
        return _add_bench
    from importlib import import_module

    module = {"client": "client_demo"}.get(name, name)
    return import_module(f".{module}", __name__).add_parser


def _command_named(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names first, if it is one (else the whole parser: it lists them,
    or says what is wrong)."""
    for arg in argv:
        if not arg.startswith("-"):
            return arg if arg in COMMANDS else None
        if arg != "--":
            return None  # an option before the command: --help, --version
    return None


def main(argv: Sequence[str] | None = None) -> int:
    # Before any command imports numba: every process of this one loads the same cache.
    compile_cache.configure()
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser(_command_named(argv)).parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:  # e.g. `burrforce experiment --json | head`: not an error
        sys.stdout = None  # nothing more can reach the closed pipe, not even at exit
        return 0
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"burrforce {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        # What the control plane refuses (an unknown phantom or library file given to
        # `serve --bone`) says why, as it would over REST, not with a traceback.
        from ..api.errors import ApiError

        if not isinstance(exc, ApiError):
            raise
        print(f"burrforce {args.command}: error: {exc.detail}", file=sys.stderr)
        return 2

