"""Run ``compile_jobs`` in parallel processes, with a progress bar while anything compiles.

Each job runs in a process of a pool (``spawn``: the caller may have threads), as soon as the
jobs it names in ``after`` are done. The processes report every kernel numba compiles
(``numba:compile`` events) to this one, which draws the bar: on a terminal a tqdm bar (what
is compiling, kernels done of about how many, elapsed, an estimate), else a plain line per
job. Kernels that load from the cache report nothing, so a warm cache shows nothing.
"""

from __future__ import annotations

import multiprocessing
import os
import queue as queue_module
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from typing import TextIO

from .compile_jobs import JOBS, Job

#: Jobs by name.
BY_NAME: dict[str, Job] = {job.name: job for job in JOBS}


@dataclass
class JobResult:
    """What a job did in its process: seconds, kernels compiled (not loaded), and every
    cached kernel of the modules it loaded, as (module.name, in the cache)."""

    name: str
    seconds: float
    compiled: int
    kernels: list[tuple[str, bool]] = field(default_factory=list)


def default_processes() -> int:
    """One process per core this process may run on, at most 4 (more jobs than that never
    run at once: see ``compile_jobs.JOBS``)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, 4))


def run_jobs(names: Sequence[str], processes: int, say: Callable[[str], None],
             bar: bool | None = None, nice: int = 0, stream: TextIO | None = None,
             header: str = "",
             on_finished: Callable[[str], None] | None = None) -> list[JobResult]:
    """Run the jobs ``names`` (and nothing else: a job named in another's ``after`` but not
    in ``names`` is taken as done) in ``processes`` processes; their results in the order
    they finished. ``say`` gets one line per job when there is no bar; ``bar`` None: a bar
    if ``stream`` (default: standard output) is a terminal with a width, drawn there.
    ``nice``: added to the processes' niceness. ``header``: said before the first kernel
    compiles (never, when every kernel loads from the cache). ``on_finished``: called with
    each job's name as it finishes (in this thread).

    Raises what a job raised (the others are stopped first)."""
    unknown = [n for n in names if n not in BY_NAME]
    if unknown:
        raise ValueError(f"unknown compile jobs: {', '.join(unknown)}")
    stream = sys.stdout if stream is None else stream
    bar = _on_a_terminal(stream) if bar is None else bar
    context = multiprocessing.get_context("spawn")
    events = context.SimpleQueue()
    pending = [BY_NAME[n] for n in names]
    done: set[str] = {j.name for j in JOBS if j.name not in names}
    running: dict[Future, Job] = {}
    results: list[JobResult] = []
    progress = _Progress(sum(j.kernels for j in pending), bar, say, stream, header)
    processes = max(1, min(processes, len(pending)))
    pool = ProcessPoolExecutor(max_workers=processes, mp_context=context,
                               initializer=_init_process, initargs=(events, nice))
    try:
        while pending or running:
            # No more than a process each: a job waiting in the pool's queue would go
            # before one that becomes ready (and comes first in JOBS) meanwhile.
            ready = [j for j in pending if set(j.after) <= done]
            for job in ready[:processes - len(running)]:
                pending.remove(job)
                running[pool.submit(_run_job, job.name)] = job
                progress.started(job.name)
            finished, _ = wait(running, timeout=0.1, return_when=FIRST_COMPLETED)
            progress.drain(events)
            for future in finished:
                job = running.pop(future)
                result = future.result()
                done.add(job.name)
                results.append(result)
                progress.finished(result)
                if on_finished is not None:
                    on_finished(job.name)
    except BaseException:
        for future in running:
            future.cancel()
        for process in list(getattr(pool, "_processes", {}).values()):
            process.terminate()  # a job compiling for a minute would hold the exit
        pool.shutdown(wait=True)
        raise
    finally:
        progress.drain(events)
        progress.close()
    # Without waiting for the processes to exit (~0.4 s of interpreter teardown each, on a
    # first start's critical path): they have nothing left to do, and end by themselves.
    pool.shutdown(wait=False)
    return results


def _on_a_terminal(stream: TextIO) -> bool:
    """``stream`` is a terminal with a width (a pseudo-terminal without one, as ``script``
    or some CI runners make, would draw the bar as nothing: lines there)."""
    try:
        return stream.isatty() and os.get_terminal_size(stream.fileno()).columns > 0
    except (OSError, ValueError, AttributeError):
        return False


class _Progress:
    """The bar (tqdm, on a terminal) or the plain lines. Nothing at all until a kernel is
    compiled: loading from the cache is not worth a word."""

    def __init__(self, total: int, bar: bool, say: Callable[[str], None],
                 stream: TextIO, header: str = "") -> None:
        self.total = max(total, 1)
        self.stream = stream
        self.header = header
        self.bar = bar
        self.say = say
        self.running: list[str] = []
        self.compiled = 0
        self.last_kernel = ""
        self._tqdm = None
        self._t0 = time.monotonic()

    def started(self, name: str) -> None:
        self.running.append(name)
        self._describe()

    def drain(self, events) -> None:
        n = 0
        while True:
            try:
                if events.empty():
                    break
                _, kernel = events.get()
            except (OSError, EOFError, queue_module.Empty):
                break
            n += 1
            self.last_kernel = kernel
        if n:
            if not self.compiled and self.header:
                self.say(self.header)
            self.compiled += n
            self._show()
            if self._tqdm is not None:
                if self.compiled > self._tqdm.total:
                    self._tqdm.total = self.compiled
                self._tqdm.update(n)
                self._describe()

    def finished(self, result: JobResult) -> None:
        self.running.remove(result.name)
        if result.compiled and not self.bar:
            self.say(f"  compiled {result.name}: {result.compiled} kernels in "
                     f"{result.seconds:.1f} s ({time.monotonic() - self._t0:.0f} s so far)")
        self._describe()

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()

    def _show(self) -> None:
        if self._tqdm is not None or not self.bar:
            return
        from tqdm import tqdm

        self._tqdm = tqdm(total=self.total, unit=" kernels", file=self.stream, leave=True,
                          dynamic_ncols=True, initial=0,
                          bar_format="{desc}: {bar} {n_fmt}/~{total_fmt} kernels "
                                     "[{elapsed}<{remaining}]")
        self._t0 = time.monotonic()

    def _describe(self) -> None:
        if self._tqdm is not None:
            what = ", ".join(self.running) or "done"
            kernel = self.last_kernel.rsplit(".", 1)[-1]
            self._tqdm.set_description_str(f"compiling {what} ({kernel})" if kernel
                                           else f"compiling {what}", refresh=True)


# --- in the pool's processes -----------------------------------------------------------

_events = None
#: Kernels numba compiled in this process so far.
_compiled = 0


def _init_process(events, nice: int) -> None:
    global _events
    _events = events
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass
    from numba.core import event

    class Listener(event.Listener):
        """Counts and reports the kernels numba compiles in this process."""

        def on_start(self, ev) -> None:
            pass

        def on_end(self, ev) -> None:
            global _compiled
            _compiled += 1
            func = getattr(ev.data.get("dispatcher"), "py_func", None)
            name = f"{func.__module__}.{func.__qualname__}" if func is not None else "?"
            try:
                _events.put(("compiled", name))
            except (OSError, ValueError):
                pass

    event.register("numba:compile", Listener())


#: How much lower the priority of a process running any job but the longest: when more
#: processes than cores want to run (a first ``serve``'s own imports and hot loop beside
#: two compile processes), the longest job, which the start waits for, keeps its core and
#: the others, which have time to spare, yield. Once lowered it stays lowered (only root may
#: raise it again): the longest job is submitted first, so it never lands on such a process
#: while the others still run.
SHORTER_JOBS_NICE = 5
_lowered = False


def _run_job(name: str) -> JobResult:
    global _lowered
    job = BY_NAME[name]
    if not job.longest and not _lowered:
        _lowered = True
        try:
            os.nice(SHORTER_JOBS_NICE)
        except OSError:
            pass
    before = _compiled
    t0 = time.perf_counter()
    job.run()
    return JobResult(name, time.perf_counter() - t0, _compiled - before, cached_kernels())


def cached_kernels() -> list[tuple[str, bool]]:
    """Every ``cache=True`` numba kernel in the burrforce modules imported so far, as
    (module.name, in the cache). A kernel only ever called from other kernels is compiled
    into them, and written to the cache when they are compiled, so "in the cache" is its
    index file being there, not its having run in this process (a caller loaded from the
    cache does not load its callees)."""
    from numba.core.caching import NullCache
    from numba.core.registry import CPUDispatcher

    found = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith("burrforce.") or module is None:
            continue
        for name, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher) and value._cache is not None \
                    and not isinstance(value._cache, NullCache) \
                    and value.py_func.__module__ == module_name:
                index = getattr(getattr(value._cache, "_cache_file", None), "_index_path", "")
                found[f"{module_name.removeprefix('burrforce.')}.{name}"] = \
                    bool(value.signatures) or (bool(index) and os.path.exists(index))
    return sorted(found.items())
