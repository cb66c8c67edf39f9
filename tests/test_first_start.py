"""A first start on a machine: the kernels a session needs compiled in parallel processes
with progress shown (and nothing shown when they load from the cache), the rest compiled
behind the running server, the cache marked complete only when every job has run, and a hot
loop that warmed only its own burr loading the other burr's tick off the packet path when
the tool changes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
import time

import pytest

from burrforce.server import compile_cache
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.cli.compile_jobs import FIRST_START, JOBS
from burrforce.server.cli.compile_run import run_jobs


def test_the_complete_mark_is_per_cache_and_cpu(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CPU_NAME", raising=False)
    assert not compile_cache.is_complete(tmp_path)
    compile_cache.mark_complete(tmp_path)
    assert compile_cache.is_complete(tmp_path)
    assert not compile_cache.is_complete(tmp_path / "other")
    monkeypatch.setenv("NUMBA_CPU_NAME", "generic")  # an image's cache for any machine
    assert not compile_cache.is_complete(tmp_path)


def test_the_complete_mark_is_per_checkout_and_source_times(tmp_path, monkeypatch):
    """numba keeps each checkout's kernels apart (by the source folder's path) and treats a
    source whose time changed as stale: the mark says complete only for the sources that
    were compiled, and keeps every checkout's mark."""
    package = tmp_path / "src" / "pkg"
    package.mkdir(parents=True)
    (package / "__init__.py").write_text("")
    kernel = package / "kernels.py"
    kernel.write_text("import numba\n")
    roots = ((package, "pkg"),)
    stamp = compile_cache.sources_stamp(roots)
    assert compile_cache.sources_stamp(roots) == stamp
    os.utime(kernel, ns=(0, kernel.stat().st_mtime_ns + 10**9))  # checked out again
    assert compile_cache.sources_stamp(roots) != stamp
    clone = tmp_path / "clone" / "pkg"
    shutil.copytree(package, clone)
    assert compile_cache.sources_stamp(((clone, "pkg"),)) != stamp  # another checkout

    cache = tmp_path / "cache"
    monkeypatch.setattr(compile_cache, "sources_stamp", lambda: "aaaaaaaaaaaa")
    compile_cache.mark_complete(cache)
    assert compile_cache.is_complete(cache)
    monkeypatch.setattr(compile_cache, "sources_stamp", lambda: "bbbbbbbbbbbb")
    assert not compile_cache.is_complete(cache)  # this checkout's kernels are not there
    compile_cache.mark_complete(cache)
    assert compile_cache.is_complete(cache)
    monkeypatch.setattr(compile_cache, "sources_stamp", lambda: "aaaaaaaaaaaa")
    assert compile_cache.is_complete(cache)  # the first checkout's mark is kept


def test_one_compiler_fills_a_cache_at_a_time(tmp_path):
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from pathlib import Path
            from burrforce.server import compile_cache
            with compile_cache.filling(directory=Path({str(tmp_path)!r})) as held:
                print(held, flush=True)
                sys.stdin.readline()
            """)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "True"
        with compile_cache.filling(wait=False, directory=tmp_path) as held:
            assert held is False
        t0 = time.monotonic()
        assert compile_cache.wait_for_filler(0.3, tmp_path) is False
        assert time.monotonic() - t0 >= 0.3
        # A compiler that waits says so first, then gets the lock once it is let go.
        import threading

        said, got = [], []

        def second() -> None:
            with compile_cache.filling(directory=tmp_path, on_wait=lambda: said.append(1)) \
                    as held:
                got.append(held)

        waiter = threading.Thread(target=second)
        waiter.start()
        time.sleep(0.3)
        assert said == [1] and got == []
        holder.stdin.write("\n")
        holder.stdin.flush()
        holder.wait(timeout=30)
        waiter.join(timeout=30)
        assert got == [True]
        assert compile_cache.wait_for_filler(5.0, tmp_path) is True
        with compile_cache.filling(wait=False, directory=tmp_path) as held:
            assert held is True
    finally:
        holder.kill()


def test_every_first_start_job_is_a_job_and_waits_only_for_jobs():
    names = {job.name for job in JOBS}
    assert set(FIRST_START) <= names
    for job in JOBS:
        assert set(job.after) <= names and job.name not in job.after
        assert job.kernels > 0


#: A short job (seconds on an empty cache) for what any job's progress shows.
SHORT = "bone files"


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))  # the pool's processes inherit it
    return cache


def test_compiling_shows_each_job_and_loading_shows_nothing(empty_cache, capsys):
    lines: list[str] = []
    finished: list[str] = []
    results = run_jobs([SHORT], 1, lines.append, bar=False, header="first use",
                       on_finished=finished.append)
    assert [r.name for r in results] == [SHORT] and finished == [SHORT]
    assert results[0].compiled > 5
    assert len(lines) == 2 and lines[0] == "first use" and lines[1].startswith(
        f"  compiled {SHORT}: {results[0].compiled} kernels in ")
    # The same job again: every kernel loads from the cache, and nothing is said, not even
    # the header.
    lines.clear()
    again = run_jobs([SHORT], 1, lines.append, bar=False, header="first use")
    assert again[0].compiled == 0 and lines == []
    assert capsys.readouterr().out == ""


def test_the_bar_names_what_compiles_with_a_count_and_an_estimate(empty_cache, capsys):
    run_jobs([SHORT], 1, print, bar=True)
    out = capsys.readouterr().out
    assert f"compiling {SHORT}" in out
    assert "kernels [" in out and "<" in out  # n/~total kernels [elapsed<remaining]


def test_a_job_that_fails_fails_the_run(empty_cache):
    with pytest.raises(ValueError, match="unknown compile jobs: nope"):
        run_jobs(["nope"], 1, print, bar=False)


#: Run in a process of its own: which ticks a process has warmed is per process.
_TOOL_CHANGE = textwrap.dedent("""
    import threading, socket
    from numba.core import event
    from burrforce.server import compile_cache
    from burrforce.server.bone.engine import tick_warmed
    from burrforce.server.bone import phantom
    from burrforce.server.bone.shared import publish, run_directory
    from burrforce.server.hotloop.commands import COMMANDS, CommandContext
    from burrforce.server.hotloop.dispatch import Dispatcher
    from burrforce.server.hotloop.spec import SessionSpec, build_session
    from burrforce.server.model.params import CuttingParams
    from burrforce.server.model.shapes import Burr, Cylinder, Fluted

    assert not compile_cache.is_complete()
    ref = publish(phantom("workpiece", 0.5), run_directory(), "t")
    dispatcher = Dispatcher()
    dispatcher.add(build_session(SessionSpec(bone=ref)))
    dispatcher.warm_up()
    shaped = CuttingParams().with_(burr=Burr(Cylinder(2.0, 3.0), Fluted(6)))
    print("warmed", tick_warmed(CuttingParams()), tick_warmed(shaped), flush=True)

    compiled = []
    class Count(event.Listener):
        def on_start(self, ev): pass
        def on_end(self, ev): compiled.append(ev.data["dispatcher"].py_func.__name__)
    event.register("numba:compile", Count())
    ctx = CommandContext(dispatcher, threading.Lock(), threading.Event(),
                         socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
    COMMANDS["set_engine"](ctx, {"session_id": 1, "params": shaped})
    print("after the change", tick_warmed(shaped), flush=True)
    engine = dispatcher.sessions[1].engine
    before = len(compiled)
    import numpy as np
    engine.step_raw(np.full(3, -1e5), np.array([0.0, 0.0, 1.0]), np.zeros(3), 1e5)
    print("compiled by the next tick", len(compiled) - before, flush=True)
    """)


def test_a_tool_change_loads_the_other_tick_before_the_burr_changes(tmp_path):
    """A hot loop on a cache that is not complete warms its session's round burr only; a
    change to a shaped burr (the command the control plane sends) loads that tick outside
    the loop's lock, so the tick after it compiles nothing."""
    source = compile_cache.cache_dir()
    assert source is not None and compile_cache.is_complete(source)  # conftest filled it
    cache = tmp_path / "cache"
    shutil.copytree(source, cache, ignore=shutil.ignore_patterns("complete-*", "*.lock"))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    done = subprocess.run([sys.executable, "-c", _TOOL_CHANGE], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "warmed True False" in done.stdout
    assert "after the change True" in done.stdout
    assert "compiled by the next tick 0" in done.stdout


#: The start of a script run in a process of its own: ``compiled`` lists the kernels numba
#: compiles there.
_COUNT_COMPILES = textwrap.dedent("""
    from numba.core import event
    compiled = []
    class Count(event.Listener):
        def on_start(self, e): compiled.append(e.data["dispatcher"].py_func.__qualname__)
        def on_end(self, e): pass
    event.register("numba:compile", Count())
""")


def test_after_the_first_start_jobs_a_hot_loop_and_the_default_bone_compile_nothing(tmp_path):
    """What ``serve`` compiles before it is ready (the round tick in one process, the packet
    path, the sessions without a tick and the phantoms in another) is all its hot loop's
    warm-up and its default bone's build then run: they load, nothing compiles."""
    cache = tmp_path / "cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    compile_first = ("from burrforce.server.cli.compile_jobs import FIRST_START\n"
                     "from burrforce.server.cli.compile_run import run_jobs\n"
                     "if __name__ == '__main__':\n"
                     "    run_jobs(FIRST_START, 2, print, bar=False)\n")
    script = tmp_path / "first.py"
    script.write_text(compile_first)
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stdout + done.stderr
    serve_like = _COUNT_COMPILES + textwrap.dedent("""
        from burrforce.server.bone import phantom
        from burrforce.server.bone.shared import publish, run_directory
        from burrforce.server.hotloop.dispatch import Dispatcher
        from burrforce.server.hotloop.spec import SessionSpec, build_session
        ref = publish(phantom("temporal"), run_directory(), "first")
        dispatcher = Dispatcher()
        dispatcher.add(build_session(SessionSpec(bone=ref)))
        dispatcher.warm_up()
        print("compiled", compiled)
    """)
    done = subprocess.run([sys.executable, "-c", serve_like], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "compiled []" in done.stdout, done.stdout


#: The round tick in a process of its own, on the cache ``NUMBA_CACHE_DIR``: which kernels it
#: compiled, and a hash of its outputs along a groove into the compile's workpiece.
_ROUND_TICK = _COUNT_COMPILES + textwrap.dedent("""
    import hashlib
    import numpy as np
    from burrforce.server.cli.compile_jobs import _shared_workpiece, _tick_round
    from burrforce.server.hotloop.spec import SessionSpec, build_session
    _tick_round()
    print("compiled", compiled)
    digest = hashlib.sha256()
    with _shared_workpiece() as ref:
        engine = build_session(SessionSpec(bone=ref)).engine
        top = np.argwhere(engine.grid.density > 128).max(axis=0) * engine.grid.spacing_mm
        axis = np.array([0.3, 0.0, 0.954]) / np.linalg.norm([0.3, 0.0, 0.954])
        for t in range(300):  # the burr's centre 0.5 mm above the top face: it cuts
            centre = np.array([0.5 * top[0] - 1.0 + 0.01 * t, 0.5 * top[1], top[2] + 0.5])
            engine.step_raw(centre, axis, np.array([1.0, 0.0, 0.0]), 60_000.0)
            for values in (engine.out, engine.shaft_out, engine.touch):
                digest.update(values.tobytes())
        digest.update(engine.grid.swept.tobytes())
        print("cut", int(engine.grid.swept.astype(np.int64).sum()))
    print("outputs", digest.hexdigest())
""")


def _round_tick(cache) -> dict[str, str]:
    done = subprocess.run([sys.executable, "-c", _ROUND_TICK], capture_output=True, text=True,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(cache)}, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    return dict(line.split(" ", 1) for line in done.stdout.splitlines())


def test_the_round_ticks_bone_and_parts_compiled_elsewhere_are_loaded_and_change_nothing(
        tmp_path):
    """A first start splits the round tick's compile between two processes: the tick's job
    compiles the carve on example values first (``bone.tick_parts``), then the rest, loading
    what the other job compiled meanwhile — the bone it warms the tick on and the kernels it
    reaches last. With those in the cache the tick's job compiles none of them again, and
    although a kernel from the cache may stay a call where one compiled alongside would be
    inlined, the tick gives the same outputs, to the last bit, as a tick compiled alone."""
    from burrforce.server.bone.tick_parts import round_tick_first_parts, round_tick_last_parts
    from burrforce.server.cli.compile_jobs import TICK_ROUND_PARTS

    parts_first = tmp_path / "parts-first"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(parts_first)}
    script = tmp_path / "parts.py"
    script.write_text("from burrforce.server.cli.compile_run import run_jobs\n"
                      "if __name__ == '__main__':\n"
                      f"    run_jobs([{TICK_ROUND_PARTS!r}], 1, print, bar=False)\n")
    done = subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    after_parts = _round_tick(parts_first)
    alone = _round_tick(tmp_path / "alone")
    compiled_alone = eval(alone["compiled"])
    compiled_after = eval(after_parts["compiled"])
    last = {kernel.py_func.__qualname__ for kernel, _ in round_tick_last_parts()}
    (first,) = (kernel.py_func.__qualname__ for kernel, _ in round_tick_first_parts())
    assert last <= set(compiled_alone)  # the tick calls every one of them
    assert not last & set(compiled_after), compiled_after
    # The bone's brick counts were compiled with it, not by the tick's job.
    assert "count_bricks" in compiled_alone and "count_bricks" not in compiled_after
    # The carve, compiled first for the example's types, is the one the tick calls.
    assert compiled_alone.count(first) == compiled_after.count(first) == 1
    assert int(alone["cut"]) > 0
    assert after_parts["cut"] == alone["cut"] and after_parts["outputs"] == alone["outputs"]


def test_a_first_serve_compiles_with_progress_then_the_rest_behind_it(tmp_path):
    """Empty cache and HOME: serve compiles what its session needs (a line per job when not
    on a terminal), gets ready, and fills the rest of the cache in the background, which
    marks it complete; the next start says nothing about compiling."""
    home = tmp_path / "home"
    home.mkdir()
    cache = tmp_path / "cache"
    env = {"HOME": str(home), "NUMBA_CACHE_DIR": str(cache), "XDG_CACHE_HOME": ""}
    serve = spawn_serve(tmp_path, env=env, timeout_s=600)
    try:
        banner = serve.banner
        assert "first start on this machine: compiling" in banner
        assert "  compiled tick, round burr: " in banner
        deadline = time.monotonic() + 600
        while not compile_cache.is_complete(cache) and time.monotonic() < deadline:
            time.sleep(1.0)
    finally:
        code, after = serve.stop()
    assert code == 0, banner + after
    assert "compiling the other kernels in the background" in banner + after
    assert compile_cache.is_complete(cache), (tmp_path / "data" / "compile.log").read_text()
    again = spawn_serve(tmp_path, env=env, timeout_s=120)
    code, after = again.stop()
    assert code == 0
    printed = again.banner + after
    assert "first start" not in printed and "compiling" not in printed
    assert "compiled " not in printed
