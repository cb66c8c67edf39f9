"""``burrforce experiment`` and ``burrforce bench model`` as a user runs them."""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from burrforce.server.cli import main

ROOT = Path(__file__).resolve().parents[1]

JSON_KEYS = {"orientation", "angle_deg", "feed_N", "lateral_N", "normal_N", "force_N",
             "torque_Nmm", "power_W", "mean_speed_m_s"}


def test_experiment_prints_the_nine_cases(capsys):
    assert main(["experiment"]) == 0
    out = capsys.readouterr().out
    for orientation in ("parallel", "perpendicular", "diagonal"):
        assert out.count(orientation) == 3
    assert "|F| N" in out and "speed m/s" in out


def test_experiment_json_is_stable(capsys):
    assert main(["experiment", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 9
    for row in rows:
        assert set(row) == JSON_KEYS
        assert row["orientation"] in ("parallel", "perpendicular", "diagonal")
        assert len(row["force_N"]) == 3 and len(row["torque_Nmm"]) == 3
    parallel = {r["angle_deg"]: r for r in rows if r["orientation"] == "parallel"}
    assert parallel[60.0]["normal_N"] > parallel[30.0]["normal_N"]


def test_experiment_options_reach_the_model(capsys):
    main(["experiment", "--json", "--angles", "45"])
    base = json.loads(capsys.readouterr().out)
    main(["experiment", "--json", "--angles", "45", "--us", "1610.2", "--feed-mm-s", "1.5"])
    same = json.loads(capsys.readouterr().out)  # 2×Us and ½×feed cancel
    for a, b in zip(base, same, strict=True):
        assert b["feed_N"] == pytest.approx(a["feed_N"], rel=1e-9)
    main(["experiment", "--json", "--angles", "45", "--spin", "reverse", "--k", "0"])
    rev = json.loads(capsys.readouterr().out)
    main(["experiment", "--json", "--angles", "45", "--k", "0"])
    fwd = json.loads(capsys.readouterr().out)
    for a, b in zip(fwd, rev, strict=True):
        assert b["force_N"] == pytest.approx([-x for x in a["force_N"]], abs=1e-12)
    main(["experiment", "--json", "--angles", "45", "--elements", "200"])
    assert len(json.loads(capsys.readouterr().out)) == 3


def test_experiment_writes_the_plot(tmp_path, capsys):
    path = tmp_path / "fig" / "experiment.png"
    assert main(["experiment", "--plot", str(path)]) == 0
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert str(path) in capsys.readouterr().err


def test_experiment_below_cutting_speed_warns(capsys):
    assert main(["experiment", "--rpm", "1000", "--json"]) == 0
    captured = capsys.readouterr()
    assert "below the minimum cutting speed" in captured.err
    assert all(r["force_N"] == [0.0, 0.0, 0.0] for r in json.loads(captured.out))


@pytest.mark.parametrize(
    ("args", "message"),
    [(["--angles", "0,30"], "(0, 90]"),
     (["--angles", "thirty"], "comma-separated"),
     (["--radius-mm", "-2"], "> 0"),
     (["--rpm", "nan"], "finite"),
     (["--elements", "3"], "8..1000000"),
     (["--spin", "left"], "invalid choice")],
)
def test_experiment_bad_arguments_say_what_is_wrong(capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        main(["experiment", *args])
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


def test_experiment_depth_beyond_the_burr_is_an_error(capsys):
    assert main(["experiment", "--depth-mm", "5"]) == 2
    assert "exceeds the burr diameter" in capsys.readouterr().err


def test_bench_model_quick_writes_its_results(tmp_path, capsys):
    assert main(["bench", "model", "--quick", "--repeats", "3", "--out", str(tmp_path)]) == 0
    md = (tmp_path / "model.md").read_text()
    assert "(default)" in md and "Target:" in md
    rows = json.loads((tmp_path / "model.json").read_text())["rows"]
    assert {r["refine"] for r in rows} == {1, 2, 3}
    assert all(r["median_us"] > 0 and 0 <= r["max_error_rel"] < 0.05 for r in rows)
    assert (tmp_path / "model.png").read_bytes()[:4] == b"\x89PNG"


def test_console_script_runs():
    out = subprocess.run([sys.executable, "-m", "burrforce.server.cli", "--version"],
                         capture_output=True, text=True, check=True)
    assert out.stdout.startswith("burrforce ")


def test_unwritable_plot_path_fails_before_the_work(capsys):
    assert main(["experiment", "--plot", "/proc/no-such-dir/x.png"]) == 2
    captured = capsys.readouterr()
    assert "cannot write the plot to /proc/no-such-dir/x.png" in captured.err
    assert captured.out == ""  # nothing computed or printed first


def test_output_piped_into_head_is_not_an_error():
    # 270 rows (~80 kB) outgrow the pipe's buffer, so the write really meets the closed pipe.
    angles = ",".join(str(a) for a in range(1, 91))
    cmd = (f"{sys.executable} -m burrforce.server.cli experiment --json --elements 128 "
           f"--angles {angles} | head -c 10")
    out = subprocess.run(["bash", "-o", "pipefail", "-c", cmd], capture_output=True, text=True)
    assert "Broken pipe" not in out.stderr and "Traceback" not in out.stderr
    assert out.returncode == 0


ACCURACY_KEYS = {"voxel_mm", "elements", "orientation", "angle_deg", "error_rel", "ripple_rel",
                 "tick_p50_us", "tick_p99_us"}


def test_bench_accuracy_json_and_results_file(tmp_path, capsys):
    assert main(["bench", "accuracy", "--voxel-mm", "0.4", "--elements", "512",
                 "--measure-mm", "0.3", "--no-oblique", "--no-plot", "--json",
                 "--out", str(tmp_path)]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 9
    for row in rows:
        assert ACCURACY_KEYS <= set(row)
        assert row["voxel_mm"] == 0.4 and row["elements"] == 512
        assert abs(row["error_rel"]) < 0.2 and row["tick_p99_us"] > 0
    table = (tmp_path / "accuracy.md").read_text()
    assert "| aligned | 0.4 | 512 |" in table
    saved = json.loads((tmp_path / "accuracy.json").read_text())
    assert saved["rows"] == rows
    assert saved["baseline"] == []  # no earlier results in tmp_path: nothing to compare


@pytest.mark.parametrize("argv", [["--voxel-mm", "0"], ["--elements", "10"],
                                  ["--elements", "a,b"]])
def test_bench_accuracy_rejects_bad_options(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench", "accuracy", *argv])
    assert exc.value.code == 2
    assert "error" in capsys.readouterr().err


def test_serve_demo_starts_over_the_loaded_bone():
    from burrforce.server.bone import phantom
    from burrforce.server.cli.serve_demo import demo_start_mm

    grid = phantom("workpiece", 0.5).grid  # the block: x 0–26, y −8–8 mm
    info = {"shape": list(grid.shape), "spacing_mm": grid.spacing_mm.tolist(),
            "origin_mm": grid.origin_mm.tolist(), "direction": grid.direction.tolist()}
    x, y = demo_start_mm(info)
    assert 0.0 < x and x + 10.0 < 26.0 and abs(y) < 1.0
    assert demo_start_mm(None) == (-5.0, 0.0)


def test_bench_accuracy_in_a_checkout_leaves_git_status_clean(tmp_path):
    """Run as a user would, inside a checkout (its tracked results page and .gitignore): the
    page stays as it is, the run's results go to a fresh folder of its own, named on stderr,
    and ``git status`` stays clean."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args],
                              cwd=tmp_path, check=True, capture_output=True, text=True).stdout

    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "accuracy.md").write_text("the tracked page\n")
    (tmp_path / ".gitignore").write_text((ROOT / ".gitignore").read_text())
    git("init", "-q")
    git("add", ".")
    git("commit", "-q", "-m", "checkout")
    out = subprocess.run(
        [sys.executable, "-m", "burrforce.server.cli", "bench", "accuracy", "--voxel-mm", "0.4",
         "--elements", "512", "--measure-mm", "0.3", "--no-oblique", "--no-plot",
         "--no-edges"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert git("status", "--porcelain", "--untracked-files=all") == ""
    assert [p.name for p in (tmp_path / "benchmarks").iterdir()] == ["accuracy.md"]
    (fresh,) = tmp_path.glob("burrforce-bench-accuracy-*")
    assert sorted(p.name for p in fresh.iterdir()) == ["accuracy.json", "accuracy.md"]
    assert fresh.name in out.stderr and "| aligned | 0.4 | 512 |" in out.stdout


def test_the_parser_leaves_the_slow_scipy_modules_to_the_commands_that_use_them():
    """The whole parser (``burrforce --help``) imports every command's module, so what they
    import at the top delays it: scipy.integrate (the reference model) and scipy.stats (the
    calibration fit) are imported where they are used."""
    assert _imported("from burrforce.server.cli import build_parser\n"
                     "build_parser()\n",
                     ("scipy.integrate", "scipy.stats", "scipy.optimize")) == []


def _imported(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of ``modules`` a new interpreter has imported after running ``code``."""
    code += f"import sys\nprint(sorted(m for m in {modules!r} if m in sys.modules))\n"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.replace("'", '"'))


def test_serve_spawns_its_hot_loops_before_numba_the_bone_or_the_web_stack_load():
    """`burrforce serve` builds its own parser only, and what it runs up to spawning its hot
    loops imports neither numba, nor the bone, nor FastAPI: their interpreters start ~0.7 s
    sooner, beside this one's imports."""
    assert _imported("from burrforce.server.cli import _command_named, build_parser\n"
                     "from burrforce.server.cli.serve import main\n"
                     "build_parser(_command_named(['serve', '--demo'])).parse_args(['serve'])\n"
                     "from burrforce.server.api.data_lock import DataDirLock\n"
                     "from burrforce.server.hotloop.pool import spawn_pool\n",
                     ("numba", "burrforce.server.bone", "fastapi", "scipy")) == []


def test_a_command_alone_parses_and_helps_as_in_the_whole_parser():
    from burrforce.server.cli import COMMANDS, _command_named, build_parser

    assert _command_named(["serve", "--demo"]) == "serve"
    assert _command_named(["client", "demo"]) == "client"
    assert _command_named(["--help"]) is None and _command_named([]) is None
    assert _command_named(["nope"]) is None and _command_named(["--", "bench"]) == "bench"
    whole = build_parser()
    for command in COMMANDS:
        alone = build_parser(command)
        sub = next(a for a in whole._actions if a.dest == "command").choices[command]
        sub_alone = next(a for a in alone._actions if a.dest == "command").choices[command]
        assert sub_alone.format_help() == sub.format_help()
    with pytest.raises(SystemExit):
        main(["nope"])


def test_serve_counts_ready_from_the_process_start():
    """"ready in N s" counts the interpreter's start and the imports too (what a user waits)."""
    code = ("import time\n"
            "time.sleep(0.4)\n"
            "from burrforce.server.cli.invocation import process_age_s\n"
            "print(process_age_s())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert 0.4 <= float(out.stdout) < 30.0


def test_serve_counts_ready_from_its_own_start_after_a_shell_ran_other_commands_first():
    """``python3 -m venv .venv && .venv/bin/pip install -e . && .venv/bin/burrforce serve``:
    the shell execs into serve, whose process then started with the shell, before the
    install: "ready in" must not count the install."""
    code = ("from burrforce.server.cli.invocation import process_age_s; "
            "print(process_age_s())")
    script = f"sleep 3 && exec {shlex.quote(sys.executable)} -c {shlex.quote(code)}"
    out = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert 0.0 <= float(out.stdout) < 2.5  # not the 3 s the shell slept
