"""What every ``burrforce bench …`` shares: its parser's common flags (``--out``, ``--json``),
where its results go, progress on stderr, and the closing print.

Results go where ``--out`` says; without it, into a fresh folder in the current directory
named after the bench and the time (``burrforce-bench-NAME-YYYYmmdd-HHMMSS``), said on stderr
before the run. A bench never writes into a checkout's tracked ``benchmarks/`` unless told to
(the project regenerates those pages with ``--out benchmarks``).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from .timing import machine_line

Main = Callable[[argparse.Namespace], int]

#: ``--json``'s help for a bench that prints its rows.
JSON_ROWS = "print the rows as JSON on stdout (progress goes to stderr)"
#: ``--json``'s help for a bench that prints its whole result.
RESULTS_JSON = "print the results as JSON on stdout (progress goes to stderr)"


def add_bench(sub: argparse._SubParsersAction, name: str, main: Main, *, help: str,
              description: str, json_help: str | None = None) -> argparse.ArgumentParser:
    """The parser of ``bench NAME``, with ``--out`` (and ``--json`` when ``json_help`` is
    given), running ``main``; the bench adds its own flags to it."""
    p = sub.add_parser(name, help=help, description=description)
    if json_help is not None:
        p.add_argument("--json", action="store_true", help=json_help)
    p.add_argument("--out", type=Path, default=None,
                   help="results directory. Default: a new folder "
                        f"./burrforce-bench-{name}-YYYYmmdd-HHMMSS")
    p.set_defaults(func=main, bench_name=name)
    return p


def say(text: str) -> None:
    """Progress, on stderr (stdout carries the results)."""
    print(text, file=sys.stderr, flush=True)


def out_dir(args: argparse.Namespace) -> Path:
    """``--out``, else a fresh folder's name (once per run: it is stored back into ``args``).
    The bench creates it when it writes."""
    if args.out is None:
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        args.out = Path(f"burrforce-bench-{args.bench_name}-{stamp}")
        say(f"results will be written to {args.out}/ (--out DIR to choose)")
    return args.out


def save_json(out: Path, name: str, result: dict, utc: bool = False) -> tuple[dict, Path]:
    """Write OUT/NAME.json (creating OUT): ``result`` with the run's ``date`` (local time, or
    UTC) and this ``machine`` (``timing.machine_line``). Returns what it wrote, for the page
    to quote, and where."""
    out.mkdir(parents=True, exist_ok=True)
    now = dt.datetime.now(dt.timezone.utc) if utc else dt.datetime.now()
    stamp = now.strftime("%Y-%m-%d %H:%M UTC" if utc else "%Y-%m-%d %H:%M")
    result = {**result, "date": stamp, "machine": machine_line()}
    path = out / f"{name}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    return result, path


def write_page(out: Path, name: str, lines: Sequence[str]) -> Path:
    """Write OUT/NAME.md: ``lines``, each ending in a newline. Returns its path."""
    path = out / f"{name}.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def report(args: argparse.Namespace, page: Path, *others: Path, rows: Any = None,
           indent: int = 2) -> int:
    """Print the results (``rows`` as JSON with ``--json``, else the markdown ``page``), then
    which files hold them; the command's exit status."""
    if getattr(args, "json", False) and rows is not None:
        print(json.dumps(rows, indent=indent))
    else:
        print(page.read_text())
    say("results written to " + ", ".join(str(p) for p in (page, *others)))
    return 0


def run_alone(add_parser: Callable[[argparse._SubParsersAction], None], name: str,
              argv: Sequence[str] | None = None, prog: str | None = None) -> int:
    """Run one bench outside the ``burrforce`` command (``python -m …``), with its parser and
    the command's handling of errors."""
    from .. import compile_cache

    compile_cache.configure()  # before the bench imports numba, as the command does
    parser = argparse.ArgumentParser(prog=prog or f"python -m {name}")
    sub = parser.add_subparsers(dest="bench", required=True)
    add_parser(sub)
    sub.choices[name].prog = parser.prog  # its usage line: ``prog --flags``, not ``prog NAME``
    args = parser.parse_args([name, *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args) or 0)
    except (ValueError, RuntimeError, OSError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
