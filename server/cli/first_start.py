"""A first ``serve`` on a machine: the kernels a session needs compiled before it is ready
(``compile_jobs.FIRST_START``, in parallel processes with a progress bar), the rest behind
the running server (``burrforce compile --background``)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from .. import compile_cache


def compile_first_start(say, on_packet_path: Callable[[], None] | None = None,
                        on_phantoms: Callable[[], None] | None = None) -> None:
    """Compile what a hot loop needs to serve a round burr (``compile_jobs.FIRST_START``),
    in parallel processes, with a progress bar; the rest follows once serving
    (:func:`start_filler`). Waits instead for a ``burrforce compile`` already filling the
    cache (another server's, behind its own first start).

    Called while the tick still compiles: ``on_packet_path`` once the packet path is in the
    cache, which is all a hot loop without sessions loads (``serve`` starts its loops then);
    ``on_phantoms`` once the phantoms and the bone's summaries are (``serve`` loads them into
    its own process then: :func:`load_bone_kernels`)."""
    from .compile_jobs import BUILT_IN_PHANTOMS, FIRST_START, PACKET_PATH

    def finished(name: str) -> None:
        callback = {PACKET_PATH: on_packet_path, BUILT_IN_PHANTOMS: on_phantoms}.get(name)
        if callback is not None:
            callback()

    _compile(FIRST_START, say, "first start on this machine: compiling the kernels a session "
                               "needs (once: they are cached; the rest compiles in the "
                               "background once serving)", on_finished=finished)


def compile_before_use(jobs: tuple[str, ...], what: str, stream: TextIO) -> None:
    """For a command other than ``serve`` (``report``, ``replay``) on a cache that is not
    complete: compile ``jobs`` first, saying so and drawing the bar on ``stream`` (standard
    error: the command's own output stays clean), instead of compiling in silence on first
    use. Waits instead for a ``burrforce compile`` filling the cache (a server's, behind its
    first start). Nothing at all on a complete cache."""
    if compile_cache.is_complete():
        return

    def say(text: str) -> None:
        print(text, file=stream, flush=True)

    _compile(jobs, say, f"first use on this machine: compiling the kernels {what} needs "
                        "(once: they are cached; `burrforce compile` does them all ahead)",
             stream)


def _compile(jobs: tuple[str, ...], say, header: str, stream: TextIO | None = None,
             on_finished: Callable[[str], None] | None = None) -> None:
    """Run ``jobs`` with the bar, ``header`` said when the first kernel compiles (nothing
    when all load), after any ``burrforce compile`` filling the same cache."""
    from .compile_run import default_processes, run_jobs

    with compile_cache.filling(on_wait=lambda: say(
            "  waiting for another `burrforce compile` filling the same cache "
            f"({compile_cache.cache_dir()})...")):
        run_jobs(jobs, default_processes(), say, stream=stream, header=header,
                 on_finished=on_finished)


def start_filler(say, data_dir: Path) -> subprocess.Popen | None:
    """``burrforce compile --background`` into the same cache: what the first start left out
    (the other burrs' tick, meshes, reports, devices) compiled at a lower priority, one
    process, while the server runs; its output goes to ``DATA_DIR/compile.log``."""
    try:
        data_dir.mkdir(parents=True, exist_ok=True)
        with open(data_dir / "compile.log", "ab") as log:
            process = subprocess.Popen(
                [sys.executable, "-m", "burrforce.server.cli", "compile", "--background"],
                stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True)  # its pool's processes stop with it
    except OSError as e:
        say(f"  (the other kernels were not compiled in the background: {e}; "
            "`burrforce compile` does it)")
        return None
    say("  compiling the other kernels in the background (other burrs, meshes, devices): "
        "a tool change waits for them")
    return process


def stop_filler(process: subprocess.Popen | None) -> None:
    """Stop the background compile with the server (the cache keeps what it finished; the
    next start compiles the rest behind it again)."""
    if process is None or process.poll() is not None:
        return
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(process.pid, sig)
            process.wait(timeout=wait_s)
            return
        except ProcessLookupError:
            return
        except subprocess.TimeoutExpired:
            continue


def load_bone_kernels() -> None:
    """Build a coarse phantom, which loads the phantom, brick-summary and shared-bone kernels
    the default session's load runs (best effort: the load itself loads what this missed)."""
    try:
        from ..bone import phantom

        phantom("temporal", 1.0)
    except Exception:  # only a head start: the real load reports its own errors
        pass
