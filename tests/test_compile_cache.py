"""The numba cache: where the ``burrforce`` command puts it, ``burrforce compile`` filling it,
and later processes — alone, two at once, a real ``serve`` with its hot-loop child — loading
every kernel from it without compiling (``NUMBA_DEBUG_CACHE``: "data loaded", no "data
saved")."""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server import __version__, compile_cache
from burrforce.server.bench.serve_process import spawn_serve

SAVED = "[cache] data saved"
LOADED = "[cache] data loaded"


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "NUMBA_DEBUG_CACHE", "XDG_CACHE_HOME")}
    env.update(extra)
    return env


def _compile(env: dict[str, str]) -> subprocess.Popen:
    """``burrforce compile``, printing into a file of its own: two at once, one waits on the
    fill lock for the other, and a pipe nobody reads yet would stop the one it waits for."""
    out = tempfile.TemporaryFile("w+")
    proc = subprocess.Popen([sys.executable, "-m", "burrforce.server.cli", "compile"],
                            stdout=out, stderr=subprocess.STDOUT, text=True, env=env)
    proc.printed = out  # type: ignore[attr-defined]
    return proc


def _finish(proc: subprocess.Popen) -> str:
    proc.wait(timeout=600)
    with proc.printed as f:  # type: ignore[attr-defined]
        f.seek(0)
        out = f.read()
    assert proc.returncode == 0, out
    return out


_DIRNAME = f"numba-{__version__}-{compile_cache.kernels_digest()}"


def _digest(roots) -> str:
    compile_cache.kernels_digest.cache_clear()
    try:
        return compile_cache.kernels_digest(roots)
    finally:
        compile_cache.kernels_digest.cache_clear()


def test_the_kernels_digest_follows_every_module_a_kernel_may_read(tmp_path):
    (tmp_path / "server" / "bone").mkdir(parents=True)
    (tmp_path / "server" / "api").mkdir()
    (tmp_path / "proto").mkdir()
    kernel = tmp_path / "server" / "bone" / "voxels.py"
    kernel.write_text("from numba import njit\n\nfrom ...proto.messages import POSE\n")
    layout = tmp_path / "proto" / "messages.py"  # constants a kernel compiles in
    layout.write_text("POSE = 1\n")
    route = tmp_path / "server" / "api" / "routes.py"  # imports the kernel, is none
    route.write_text("from ..bone.voxels import njit\n")
    roots = ((tmp_path / "server", "burrforce.server"), (tmp_path / "proto", "burrforce.proto"))
    first = _digest(roots)
    assert _digest(roots) == first
    route.write_text("from ..bone.voxels import njit\nROUTE = 2\n")
    assert _digest(roots) == first
    layout.write_text("POSE = 2\n")
    second = _digest(roots)
    assert second != first
    kernel.write_text("from numba import njit\n\nfrom ...proto.messages import POSE\nLIMIT = 2\n")
    assert _digest(roots) not in (first, second)


def test_the_digest_covers_the_kernels_and_what_they_import_and_nothing_else():
    modules = compile_cache.kernel_modules()
    for kernel in ("server.bone.voxels", "server.bone.carve", "server.model.kernels",
                   "server.hotloop.stages", "server.hot_kernel", "server.haptics.coupling"):
        assert f"burrforce.{kernel}" in modules
    # Constants compiled into kernels, from modules without kernels of their own.
    assert "burrforce.proto.messages" in modules
    assert "burrforce.server.model.params" in modules
    for name in modules:
        assert not name.startswith(("burrforce.server.api", "burrforce.server.cli.serve",
                                    "burrforce.server.bench.accuracy", "burrforce.server.ui",
                                    "burrforce.server.report", "burrforce.client")), name


def _source_copy(tmp_path):
    server = Path(compile_cache.__file__).resolve().parent
    shutil.copytree(server, tmp_path / "server",
                    ignore=shutil.ignore_patterns("__pycache__", "vendor"))
    shutil.copytree(server.parent / "proto", tmp_path / "proto",
                    ignore=shutil.ignore_patterns("__pycache__"))
    return ((tmp_path / "server", "burrforce.server"), (tmp_path / "proto", "burrforce.proto"))


@pytest.mark.parametrize("edited", ["api/routes_sessions.py", "bench/accuracy.py",
                                    "cli/serve.py"])
def test_editing_a_route_or_a_benchmark_keeps_the_compiled_kernels(tmp_path, edited):
    roots = _source_copy(tmp_path)
    before = _digest(roots)
    assert before == compile_cache.kernels_digest()  # the copy digests as the package does
    path = tmp_path / "server" / edited
    path.write_text(path.read_text() + "\n# an edit\n")
    assert _digest(roots) == before


@pytest.mark.parametrize("edited", ["bone/voxels.py", "model/kernels.py", "hot_kernel.py",
                                    "model/params.py"])
def test_editing_a_kernel_or_what_it_imports_renews_them(tmp_path, edited):
    roots = _source_copy(tmp_path)
    before = _digest(roots)
    path = tmp_path / "server" / edited
    path.write_text(path.read_text() + "\n# an edit\n")
    assert _digest(roots) != before


def test_default_is_under_xdg_cache_home_and_versioned(tmp_path):
    env = {"XDG_CACHE_HOME": str(tmp_path)}
    assert compile_cache.default_cache_dir(env) == tmp_path / "burrforce" / _DIRNAME
    assert compile_cache.configure(env) == tmp_path / "burrforce" / _DIRNAME
    assert env["NUMBA_CACHE_DIR"] == str(tmp_path / "burrforce" / _DIRNAME)


@pytest.mark.parametrize("xdg", [None, "", "relative/cache"])
def test_without_an_absolute_xdg_cache_home_it_is_under_home(xdg):
    env = {} if xdg is None else {"XDG_CACHE_HOME": xdg}
    assert compile_cache.configure(env) == \
        Path.home() / ".cache" / "burrforce" / _DIRNAME


@given(st.text(st.characters(blacklist_categories=("Cs",), blacklist_characters="\0"),
               min_size=1), st.one_of(st.none(), st.text(min_size=1)))
def test_numba_cache_dir_set_by_the_user_wins(cache_dir, xdg):
    env = {"NUMBA_CACHE_DIR": cache_dir}
    if xdg is not None:
        env["XDG_CACHE_HOME"] = xdg
    assert compile_cache.configure(env) == Path(cache_dir)
    assert env["NUMBA_CACHE_DIR"] == cache_dir


def test_the_command_sets_it_before_numba_is_imported(tmp_path):
    code = ("import sys\n"
            "from burrforce.server import cli\n"
            "assert 'numba' not in sys.modules, 'imported before the cache dir is set'\n"
            "try:\n"
            "    cli.main(['--version'])\n"
            "except SystemExit:\n"
            "    pass\n"
            "import numba\n"
            "print(numba.config.CACHE_DIR)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=_env(XDG_CACHE_HOME=str(tmp_path)), timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == \
        str(tmp_path / "burrforce" / _DIRNAME)


#: The Falcon's kinematics in the direction only the USB-emulated Falcon (tests/support) and
#: the tests call (pose → encoders, commands → force): no server path does, so compile leaves
#: them to their first use, and names them.
EMULATOR_ONLY = {f"server.devices.falcon.kinematics.{name}" for name in (
    "angle_to_encoder", "commands_to_torques", "end_effector_force", "inverse_kinematics")}


@pytest.fixture(scope="module")
def compiled(tmp_path_factory) -> tuple[Path, str]:
    """A cache filled from empty by two ``burrforce compile`` started at once, and what the
    one that filled it printed. The fill lock lets one compile; the other says it waits,
    then only loads what the first saved."""
    cache = tmp_path_factory.mktemp("numba-cache")
    env = _env(NUMBA_CACHE_DIR=str(cache), NUMBA_DEBUG_CACHE="1")
    outs = [_finish(p) for p in [_compile(env), _compile(env)]]
    waited = [out for out in outs if out.startswith("waiting for another `burrforce compile`")]
    filled = [out for out in outs if out not in waited]
    assert len(filled) >= 1, outs
    for out in waited:
        assert out.count(SAVED) == 0 and out.count(LOADED) > 0, out
    # (if one ended before the other began, both held the lock in turn: the second only loaded)
    return cache, max(filled, key=lambda out: out.count(SAVED))


def test_compile_fills_the_cache_it_is_given(compiled, tmp_path):
    cache, out = compiled
    assert out.count(SAVED) > 0
    indexes = list(cache.rglob("*.nbi"))
    assert len(indexes) >= out.count(SAVED) // 2 > 0  # an index per kernel, data per signature
    summary = [line for line in out.splitlines() if "cached kernels in" in line]
    assert len(summary) == 1 and str(cache) in summary[0]
    kept, total = (int(x) for x in summary[0].split(" cached")[0].split(" of "))
    named = [line.split(": ", 1)[1].split(", ") for line in out.splitlines()
             if line.startswith("not in the cache")]
    missing = set(named[0]) if named else set()
    assert 0 < kept <= total and total - kept == len(missing)  # named, not silently skipped
    assert len(missing - EMULATOR_ONLY) <= 2


def test_after_compile_processes_only_load_even_two_at_once(compiled):
    cache, _ = compiled
    before = sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*.nb*"))
    env = _env(NUMBA_CACHE_DIR=str(cache), NUMBA_DEBUG_CACHE="1")
    outs = [_finish(p) for p in [_compile(env), _compile(env)]]
    for out in outs:
        assert out.count(SAVED) == 0
        assert out.count(LOADED) > 0
    assert sorted((p, p.stat().st_mtime_ns) for p in cache.rglob("*.nb*")) == before


def test_serve_and_its_hot_loop_load_every_kernel_from_the_compiled_cache(compiled, tmp_path):
    cache, _ = compiled
    serve = spawn_serve(tmp_path, "--bone", "phantom:temporal",
                        env={"NUMBA_CACHE_DIR": str(cache), "NUMBA_DEBUG_CACHE": "1"})
    code, after = serve.stop()
    printed = serve.banner + after
    assert code == 0, printed
    assert printed.count(SAVED) == 0, printed
    # The hot loop's wire kernels run only in the child: loaded there, from this cache.
    assert f"{LOADED} from '{cache}" in printed
    assert "wire.decode_pose_into" in printed


def _small_recording(folder: Path) -> Path:
    """A short recording of a session cutting, made in this process."""
    from burrforce.proto.messages import Pose
    from burrforce.server.bone import BoneEngine, phantom
    from burrforce.server.hotloop import Session
    from burrforce.server.record import start_recording

    bone = phantom("workpiece", 0.5)
    session = Session(1, BoneEngine(bone.grid, bone.materials))
    recorder = start_recording(session, folder / "trainee")
    for seq in range(1, 40):
        pose = Pose(1, seq, seq * 1000, (5.0 + 0.02 * seq, 0.0, -0.5), (0.0, 0.0, 0.0, 1.0),
                    60_000.0, True, None, 0)
        session.admit(pose.seq)
        session.respond(pose, seq * 1_000_000)
    recorder.close()
    return recorder.path


def test_a_report_after_compile_loads_every_kernel_and_says_nothing_of_it(compiled, tmp_path):
    """`burrforce compile` covers the replay a report runs (its bone is loaded from the
    recording's snapshot, typed apart from a hot loop's shared one): the report compiles
    nothing and its output is the report alone."""
    cache, _ = compiled
    path = _small_recording(tmp_path)
    out = subprocess.run([sys.executable, "-m", "burrforce.server.cli", "report", str(path)],
                         capture_output=True, text=True, timeout=300,
                         env=_env(NUMBA_CACHE_DIR=str(cache), NUMBA_DEBUG_CACHE="1"))
    assert out.returncode == 0, out.stderr
    assert out.stdout.count(SAVED) == 0 and out.stdout.count(LOADED) > 0
    assert "first use" not in out.stdout + out.stderr
    report = [line for line in out.stdout.splitlines() if not line.startswith("[cache]")]
    assert report[0].startswith("trainee.burrrec")


def test_before_a_replay_an_incomplete_cache_is_filled_saying_so_on_the_stream_given(
        tmp_path, monkeypatch):
    """`report` and `replay` on an incomplete cache compile first, their lines on standard
    error (the stream given: stdout stays the report); on a complete cache nothing runs.
    (A short job stands in for the recordings job, which takes minutes.)"""
    from burrforce.server.cli.first_start import compile_before_use

    complete, incomplete = tmp_path / "complete", tmp_path / "incomplete"
    compile_cache.mark_complete(complete)
    said = {}
    for cache in (complete, incomplete):
        monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))  # the pool's processes inherit it
        stream = io.StringIO()
        compile_before_use(("bone files",), "a replay", stream)
        said[cache] = stream.getvalue().splitlines()
    assert said[complete] == [] and not list(complete.rglob("*.nbi"))
    assert said[incomplete][0].startswith(
        "first use on this machine: compiling the kernels a replay needs")
    assert said[incomplete][1].startswith("  compiled bone files: ")
    assert list(incomplete.rglob("*.nbi"))
