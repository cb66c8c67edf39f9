"""``burrforce calibrate`` as a user runs it: a case table, a folder of recordings (the example
of known truth), the plot, the table it writes, and clear errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from burrforce.server.calib.design import Sensitivities
from burrforce.server.calib.table import CaseRow, read_case_table, write_case_table
from burrforce.server.cli import main
from burrforce.server.model import thesis_cases

US, K = 805.1, 1.3


@pytest.fixture(scope="module")
def table(tmp_path_factory):
    """The thesis's nine cases × 5 replicates at Us = 805.1, K = 1.3, with 10 % replicate
    scatter and 0.03 N noise."""
    rng = np.random.default_rng(11)
    cases = list(thesis_cases())
    model = Sensitivities().predict(cases, US, K)
    rows = [CaseRow(c, *(m * (1 + 0.1 * rng.standard_normal())
                         + 0.03 * rng.standard_normal(3)).tolist())
            for c, m in zip(cases, model, strict=True) for _ in range(5)]
    return write_case_table(tmp_path_factory.mktemp("t") / "cases.csv", rows)


def test_the_issue_command_prints_the_promised_keys(table, capsys):
    assert main(["calibrate", "--cases", str(table), "--fit", "us,k", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {"us", "k", "us_ci", "k_ci", "rmse_N"} <= set(out)
    assert out["us_ci"][0] < US < out["us_ci"][1]
    assert out["k_ci"][0] < K < out["k_ci"][1]
    assert out["intervals"] == "replicate" and out["n_rows"] == 45


def test_fitting_us_alone_holds_k(table, capsys):
    assert main(["calibrate", "--cases", str(table), "--fit", "us", "--k", "1.3",
                 "--components", "feed,normal", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["k"] == 1.3 and out["k_fixed"] is True and out["k_ci"] is None
    assert out["components"] == ["feed", "normal"]
    assert out["residuals"]["lateral"]["fitted"] is False
    assert out["us_ci"][0] < US < out["us_ci"][1]


def test_the_text_report_and_the_plot(table, tmp_path, capsys):
    plot = tmp_path / "out" / "fit.png"
    assert main(["calibrate", "--cases", str(table), "--plot", str(plot)]) == 0
    captured = capsys.readouterr()
    assert "Us = " in captured.out and "95 % CI" in captured.out
    assert "predicts diagonal" in captured.out and "leave one case out (9 folds)" in captured.out
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert f"plot written to {plot}" in captured.err


def test_workpiece_forces_are_negated_on_request(table, tmp_path, capsys):
    rows = [CaseRow(r.case, -r.feed_N, -r.lateral_N, -r.normal_N)
            for r in read_case_table(table)]
    flipped = write_case_table(tmp_path / "flipped.csv", rows)
    assert main(["calibrate", "--cases", str(flipped), "--json"]) == 2
    assert "ON THE BURR" in capsys.readouterr().err
    assert main(["calibrate", "--cases", str(flipped), "--forces-on", "workpiece",
                 "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["us_ci"][0] < US


@pytest.mark.parametrize("args, message", [
    (["--cases", "absent.csv"], "cannot read the case table"),
    (["--cases", "{table}", "--table-out", "x.csv"], "--table-out writes the table made from"),
    (["--cases", "{table}", "--label", "2"], "--label chooses the material for --apply"),
    (["--recordings", "no-such-folder"], "is not a folder"),
])
def test_errors_name_the_problem(table, tmp_path, monkeypatch, capsys, args, message):
    monkeypatch.chdir(tmp_path)
    args = [a.replace("{table}", str(table)) for a in args]
    assert main(["calibrate", *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("burrforce calibrate: error:") and message in err


@pytest.mark.parametrize("args, message", [
    (["--fit", "k"], "--fit takes 'us' or 'us,k'"),
    (["--components", "feed,torque"], "--components takes distinct names"),
    (["--confidence", "1.5"], "confidence must be in"),
    ([], "one of the arguments --cases --recordings --make-example is required"),
])
def test_bad_options_are_argparse_errors(table, capsys, args, message):
    source = [] if not args else ["--cases", str(table)]
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", *source, *args])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_the_command_runs_as_installed(table):
    done = subprocess.run([sys.executable, "-m", "burrforce.server.cli", "calibrate",
                           "--cases", str(table), "--json"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["us"] > 0


def test_a_refused_apply_still_prints_the_fit_and_writes_the_plot(table, tmp_path, monkeypatch,
                                                                    capsys):
    monkeypatch.setenv("BURRFORCE_CONNECTION", str(tmp_path / "none.json"))
    plot = tmp_path / "fit.png"
    assert main(["calibrate", "--cases", str(table), "--plot", str(plot), "--apply"]) == 2
    captured = capsys.readouterr()
    assert "Us = " in captured.out and plot.exists()
    assert "not applied: no running server to apply to" in captured.err
    assert "BURRFORCE_CONNECTION" in captured.err
