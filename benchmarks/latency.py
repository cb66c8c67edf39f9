"""``python -m benchmarks.latency [--out benchmarks]``: ``burrforce bench latency`` (same flags,
same results) with its live-view part, ``page closed`` / ``page open`` (``latency_page``:
needs playwright and /usr/bin/chromium), which the installed command leaves out."""

from __future__ import annotations

import argparse
import os

from burrforce.server.bench import latency, runner

from . import latency_page


def main(args: argparse.Namespace) -> int:
    out = runner.out_dir(args)
    cpus = os.sched_getaffinity(0)  # the page part's CPUs (run() pins, then restores)
    result = latency.run(args.samples, args.samples_b2b, args.voxel_mm, progress=runner.say)
    failed = False
    if args.no_page:
        result["page"] = {"skipped": "--no-page"}
    else:
        try:
            result["page"] = latency_page.run(args.samples, args.voxel_mm, cpus=cpus,
                                              progress=runner.say)
        except Exception as exc:  # the other modes' results are written all the same
            failed = True
            result["page"] = {"skipped": f"failed: {type(exc).__name__}: {exc}"}
    status = latency.finish(args, result, out, latency_page.markdown(result["page"]))
    return 1 if failed else status


def add_parser(sub: argparse._SubParsersAction) -> None:
    latency.add_parser(sub).set_defaults(func=main)


if __name__ == "__main__":
    raise SystemExit(runner.run_alone(add_parser, "latency", prog="python -m benchmarks.latency"))
