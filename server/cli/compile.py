"""``burrforce compile``: compile every numba kernel the server uses into the cache, ahead of
the first ``serve`` (an install step, a container image's build); ``serve`` runs it behind a
first start too (``--background``).

The jobs (``compile_jobs``) run the code paths commands take on first use, so exactly the
signatures the server asks for are compiled, in parallel processes (``compile_run``). Then
every cached kernel of the modules they loaded is counted: one never compiled is named, so
a kernel added later without a job here does not go unnoticed. Only when every job has run
is the cache marked complete (``compile_cache.is_complete``): hot loops then warm every
burr's tick before they serve.
"""

from __future__ import annotations

import argparse
import os
import time

from .. import compile_cache
from ..argtypes import int_at_least
from .compile_jobs import JOBS
from .compile_run import default_processes, run_jobs

#: The niceness ``--background`` adds: the sessions a server runs meanwhile come first.
BACKGROUND_NICE = 10


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compile", help="compile the numba kernels into the cache (so serve starts at once)",
        description="Compile every numba kernel serve, the device loop and the benches use "
                    "into numba's cache (NUMBA_CACHE_DIR, else "
                    "$XDG_CACHE_HOME/burrforce/numba-VERSION-DIGEST), so that no later start "
                    "compiles. Kernels already in the cache are loaded, not compiled again. "
                    "The cache is for this CPU unless NUMBA_CPU_NAME is set (e.g. generic, "
                    "for an image that runs on other machines). A progress bar shows on a "
                    "terminal, a line per job otherwise.")
    p.add_argument("--quiet", action="store_true", help="print only the summary line")
    p.add_argument("--processes", type=int_at_least(1, "--processes"), default=None,
                   help="compile in this many processes at once. Default: one per core, "
                        "at most 4")
    p.add_argument("--background", action="store_true",
                   help="as serve runs it behind a first start: one process, at a lower "
                        "priority, nothing printed; exits at once if another compile is "
                        "filling the cache")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    quiet = args.quiet or args.background
    say = (lambda text: None) if quiet else (lambda text: print(text, flush=True))
    cache_dir = compile_cache.cache_dir()
    processes = args.processes or (1 if args.background else default_processes())
    waiting = f"waiting for another `burrforce compile` filling {cache_dir}..."
    with compile_cache.filling(wait=not args.background,
                               on_wait=lambda: say(waiting)) as held:
        if not held:  # --background: another compile fills the cache
            return 0
        say(f"compiling into {cache_dir or '(numba default)'} for "
            f"{os.environ.get('NUMBA_CPU_NAME') or 'this machine CPU'} in {processes} "
            "process(es) (kernels already there are only loaded)")
        t0 = time.perf_counter()
        results = run_jobs([job.name for job in JOBS], processes, say,
                           bar=False if quiet else None,
                           nice=BACKGROUND_NICE if args.background else 0)
        compile_cache.mark_complete()
    cached: dict[str, bool] = {}
    for result in results:
        for name, in_cache in result.kernels:
            cached[name] = cached.get(name, False) or in_cache
    missing = sorted(name for name, in_cache in cached.items() if not in_cache)
    if not args.background:
        print(f"{len(cached) - len(missing)} of {len(cached)} cached kernels in "
              f"{cache_dir or '(numba default)'} ({time.perf_counter() - t0:.1f} s, "
              f"{sum(r.compiled for r in results)} compiled)", flush=True)
    if missing:
        say("not in the cache (no job uses them: compiled on first use): "
            + ", ".join(missing))
    return 0
