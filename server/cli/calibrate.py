"""``burrforce calibrate``: Us and K from dynamometer data, with uncertainty and a plot."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..argtypes import float_in

_confidence = float_in(0.5, 0.999, "confidence")
_trim = float_in(0.0, 0.45, "trim fraction")
_k = float_in(0.0, 100.0, "K")


def _fit(text: str) -> tuple[str, ...]:
    parts = tuple(p.strip().lower() for p in text.split(",") if p.strip())
    if parts not in (("us",), ("us", "k"), ("k", "us")):
        raise argparse.ArgumentTypeError(f"--fit takes 'us' or 'us,k', got {text!r}")
    return parts


def _components(text: str) -> tuple[str, ...]:
    from ..calib.table import COMPONENTS

    parts = tuple(p.strip().lower() for p in text.split(",") if p.strip())
    if not parts or any(p not in COMPONENTS for p in parts) or len(set(parts)) != len(parts):
        raise argparse.ArgumentTypeError(
            f"--components takes distinct names among {','.join(COMPONENTS)}, got {text!r}")
    return parts


def add_parser(sub: argparse._SubParsersAction) -> None:
    from ..model.params import THESIS_K, CuttingParams

    p = sub.add_parser(
        "calibrate",
        help="fit Us (and K) to measured cutting forces: a case table or dynamometer recordings",
        description="Fit the specific cutting energy Us, and optionally K, to measured mean "
                    "cutting forces by linear least squares, with confidence intervals, "
                    "residuals per component and cross-validation (the thesis's: fit parallel "
                    "+ perpendicular, predict diagonal; and leave one case out). Input is a "
                    "case table (CSV, one row per replicate: orientation, angle_deg, depth_mm, "
                    "feed_mm_s, rpm, radius_mm, feed_N, lateral_N, normal_N) or a folder of "
                    "3-axis dynamometer recordings (CSV or NPZ) with a manifest.",
        epilog="Start with an example: burrforce calibrate --make-example DIR, then "
               "burrforce calibrate --recordings DIR --plot fit.png. docs/calibration.md "
               "describes the formats.")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--cases", type=Path, metavar="CSV", help="a case table")
    source.add_argument("--recordings", type=Path, metavar="DIR",
                        help="a folder of recordings; cases from its manifest.csv or the files")
    source.add_argument("--make-example", type=Path, metavar="DIR",
                        help="write an example folder of synthetic recordings of known truth "
                             "(the thesis's nine cases × 5 replicates) and stop")
    p.add_argument("--fit", type=_fit, default=("us", "k"), metavar="us|us,k",
                   help="fit Us alone (K held at --k) or Us and K. Default us,k")
    p.add_argument("--k", type=_k, default=THESIS_K,
                   help=f"K when fitting Us alone. Default {THESIS_K:g} (the thesis's)")
    p.add_argument("--components", type=_components, default=("feed", "lateral", "normal"),
                   metavar="LIST", help="force components to fit. Default feed,lateral,normal")
    p.add_argument("--confidence", type=_confidence, default=0.95,
                   help="confidence level of the intervals. Default 0.95")
    p.add_argument("--intervals", choices=("replicate", "ols"), default="replicate",
                   help="replicate: robust to whole-run scatter between replicates (each row "
                        "a cluster); ols: observations independent. Default replicate")
    p.add_argument("--spin", choices=("forward", "reverse"), default="forward",
                   help="the drill's spin in the experiment (the lateral force's sign follows "
                        "it). Default forward")
    p.add_argument("--min-cutting-rpm", type=float, default=CuttingParams.min_cutting_rpm,
                   help=argparse.SUPPRESS)
    p.add_argument("--forces-on", choices=("burr", "workpiece"),
                   help="what the forces act on: a case table holds the force on the burr "
                        "(default for --cases); a dynamometer under the bone measures the force "
                        "on the workpiece (default for --recordings; a manifest column "
                        "overrides it per file)")
    p.add_argument("--manifest", type=Path, metavar="CSV",
                   help="the recordings' manifest. Default DIR/manifest.csv if present")
    p.add_argument("--trim", type=_trim, default=0.1,
                   help="fraction of the burring region left out at each end (entry and "
                        "exit). Default 0.1")
    p.add_argument("--skip-bad", action="store_true",
                   help="fit the recordings that process and list the others, instead of "
                        "stopping at any bad file")
    p.add_argument("--table-out", type=Path, metavar="CSV",
                   help="write the case table made from the recordings")
    p.add_argument("--plot", type=Path, metavar="PNG",
                   help="write the thesis's Fig. 19/20 for the fit (needs matplotlib)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--apply", type=int, nargs="?", const=-1, metavar="SESSION",
                   help="apply the fitted Us and K to a session of the local server (the one "
                        "whose connection file `burrforce serve` wrote; default its session)")
    p.add_argument("--label", type=int, metavar="LABEL",
                   help="with --apply: the material label. Default the session's primary")
    p.add_argument("--seed", type=int, default=1, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.make_example is not None:
        return _make_example(args)
    from ..calib.design import ModelSetup, Sensitivities
    from ..calib.fit import FitOptions, calibrate, finite_or_none
    from ..calib.table import read_case_table

    if args.label is not None and args.apply is None:
        raise ValueError("--label chooses the material for --apply")
    _check_writable(args.plot)
    _check_writable(args.table_out)
    options = FitOptions(fit_k="k" in args.fit, k=args.k, components=args.components,
                         confidence=args.confidence, intervals=args.intervals)
    sens = Sensitivities(ModelSetup(spin=args.spin, min_cutting_rpm=args.min_cutting_rpm))
    folder = None
    if args.cases is not None:
        if args.table_out is not None:
            raise ValueError("--table-out writes the table made from --recordings")
        rows = read_case_table(args.cases)
        if args.forces_on == "workpiece":
            rows = [_negated(r) for r in rows]
    else:
        folder = _process(args)
        rows = folder.rows
        if args.table_out is not None:
            from ..calib.table import write_case_table

            write_case_table(args.table_out, rows)
    cal = calibrate(rows, options, sens)
    result = cal.as_dict()
    if folder is not None:
        result["recordings"] = [r.as_dict() for r in folder.reports]
        result["vibration"] = folder.vibration(args.confidence)
        result["failures"] = folder.failures
        result["recording_warnings"] = folder.warnings
    if args.plot is not None:
        from ..calib.plot import plot_calibration

        plot_calibration(cal, args.plot, sens)
    # Apply last, after everything is written: a refusal must not cost the fit.
    apply_error = None
    if args.apply is not None:
        try:
            result["applied"] = _apply(args, cal)
        except (ValueError, RuntimeError) as exc:
            apply_error = str(exc)
            result["apply_error"] = apply_error
    if args.json:
        print(json.dumps(finite_or_none(result), indent=2, allow_nan=False))
    else:
        from ..calib.report import format_calibration, format_recordings

        if folder is not None:
            print(format_recordings(folder))
            print()
        print(format_calibration(cal))
        if "applied" in result:
            a = result["applied"]
            print(f"\napplied to session {args.apply}, material {a['label']} "
                  f"({a['material']['name']}): Us = {a['material']['us_n_mm2']:.6g} N/mm², "
                  f"K = {a['material']['k']:.6g}")
    sys.stdout.flush()  # the report before what stderr adds
    if args.plot is not None:
        print(f"plot written to {args.plot}", file=sys.stderr)
    if args.table_out is not None:
        print(f"case table written to {args.table_out}", file=sys.stderr)
    if apply_error is not None:
        raise RuntimeError(f"not applied: {apply_error}")
    return 0


def _negated(row):
    from dataclasses import replace

    return replace(row, feed_N=-row.feed_N, lateral_N=-row.lateral_N, normal_N=-row.normal_N)


def _check_writable(path: Path | None) -> None:
    """Fail before the work, not after it."""
    import os

    if path is None:
        return
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"cannot write {path}: {exc.strerror}") from None
    if not os.access(path.parent, os.W_OK):
        raise OSError(f"cannot write {path}: {path.parent} is not writable")


def _process(args: argparse.Namespace):
    from ..calib.folder import process_folder

    progress = None
    if sys.stderr.isatty() and not args.json:
        from tqdm import tqdm

        bar = tqdm(total=0, unit="file", file=sys.stderr, leave=False)

        def progress(i: int, n: int, name: str) -> None:
            bar.total = n
            bar.n = i
            bar.set_description(name)
            bar.refresh()
    try:
        return process_folder(args.recordings, manifest=args.manifest,
                              forces_on=args.forces_on or "workpiece", trim_fraction=args.trim,
                              skip_bad=args.skip_bad, progress=progress)
    finally:
        if progress is not None:
            bar.close()


def _apply(args: argparse.Namespace, cal) -> dict:
    from ...client import connection
    from ...client.rest import BurrRest, RestError

    est = cal.estimate
    if not 0.0 <= est.k <= 100.0:
        raise ValueError(f"the fitted K = {est.k:.4g} is outside [0, 100], which the model "
                         "cannot take: fit Us alone (--fit us)")
    try:
        conn = connection.read()
    except ValueError:
        raise ValueError(f"no running server to apply to: no connection file at "
                         f"{connection.default_path()} (start `burrforce serve`, or set "
                         f"{connection.ENV_VAR} to the file it wrote)") from None
    session = conn.session if args.apply == -1 else args.apply
    args.apply = session
    try:
        with BurrRest.from_connection() as api:
            return api.apply_calibration(session, label=args.label, us_n_mm2=est.us,
                                         k=est.k, provenance=cal.summary())
    except RestError as exc:
        raise RuntimeError(f"the server refused the calibration: {exc}") from None


def _make_example(args: argparse.Namespace) -> int:
    from ..calib.example import write_example

    folder = write_example(args.make_example, seed=args.seed)
    print(f"wrote {folder.count} synthetic recordings of known truth (Us = "
          f"{folder.us_n_mm2:g} N/mm², K = {folder.k:g}) and {folder.manifest.name} to "
          f"{args.make_example}")
    print(f"next: burrforce calibrate --recordings {args.make_example} --plot "
          f"{args.make_example / 'fit.png'}")
    return 0
