"""Calibration over REST against the real stack: fit a case table, apply it to a session's
material, and see the cutting force a UDP client gets change by the fitted factor."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

from burrforce.client import BurrClient
from burrforce.client.connection import Connection
from burrforce.client.connection import write as write_connection
from burrforce.client.rest import BurrRest, RestError
from burrforce.proto.messages import STATUS_CUTTING
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack
from burrforce.server.calib.design import Sensitivities
from burrforce.server.calib.table import CaseRow, write_case_table
from burrforce.server.cli import main
from burrforce.server.model import thesis_cases

TOKEN = "calibration-token-0123456789"
VOXEL_MM = 0.25


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path_factory.mktemp("data"))
    with ServerStack(config, TOKEN) as s:
        yield s


@pytest.fixture(scope="module")
def rest(stack):
    with BurrRest(stack.url, TOKEN, timeout_s=120.0) as client:
        yield client


def _table(us: float, k: float, noise_N: float = 0.0, seed: int = 0) -> list[dict]:
    sens = Sensitivities()
    cases = list(thesis_cases())
    rng = np.random.default_rng(seed)
    model = sens.predict(cases, us, k)
    return [CaseRow(c, *(m + noise_N * rng.standard_normal(3)).tolist()).as_dict()
            for c, m in zip(cases, model, strict=True) for _ in range(3)]


def _steady_force(stack, s: dict, y_mm: float) -> float:
    """|F| over the last 50 of 150 packets of a 0.5 mm deep groove along +x."""
    with BurrClient(*stack.udp_address, session=s["id"], key=s.get("key"),
                    timeout_s=2.0) as c:
        out = [c.exchange((2.0, y_mm, 1.5), rpm=60_000, velocity=(3.0, 0.0, 0.0))]
        out += [c.exchange((2.0 + 0.003 * k, y_mm, 1.5), rpm=60_000, velocity=(3.0, 0.0, 0.0))
                for k in range(1, 150)]
    tail = [r.reply for r in out[-50:]]
    assert all(r.status & STATUS_CUTTING for r in tail)
    return float(np.linalg.norm(np.mean([r.force for r in tail], axis=0)))


def test_fit_answers_what_the_cli_prints(rest):
    result = rest.fit_calibration(_table(1610.0, 0.9, noise_N=0.02))
    assert result["us_ci"][0] < 1610.0 < result["us_ci"][1]
    assert result["k_ci"][0] < 0.9 < result["k_ci"][1]
    assert result["n_rows"] == 27 and result["rmse_N"] == pytest.approx(0.02, rel=0.3)
    assert "mean_differential_N" in result["cross_validation"]["thesis"]
    fixed = rest.fit_calibration(_table(1610.0, 0.9), fit="us", k=0.9)
    assert fixed["us"] == pytest.approx(1610.0, rel=1e-9) and fixed["k_fixed"] is True


def test_a_fit_applied_to_a_session_changes_the_force_it_streams(stack, rest):
    s = rest.create_session("phantom:workpiece", voxel_mm=VOXEL_MM)
    sid = s["id"]
    before = _steady_force(stack, s, -3.0)
    answer = rest.apply_calibration(sid, cases=_table(2 * 805.1, 1.3), fit="us")
    assert answer["label"] == 1 and answer["material"]["name"] == "cortical"
    assert answer["material"]["us_n_mm2"] == pytest.approx(1610.2, rel=1e-9)
    assert answer["material"]["k"] == 1.3  # fit="us" holds the material's K
    assert answer["result"]["k_fixed"] is True
    after = _steady_force(stack, s, 3.0)
    assert after / before == pytest.approx(2.0, rel=0.05)
    record = rest.calibrations(sid)["1"]
    assert record["previous"] == {"us_n_mm2": 805.1, "k": 1.3}
    assert record["fit"]["n_rows"] == 27 and record["us_n_mm2"] == answer["material"]["us_n_mm2"]
    assert rest.parameters(sid)["us_n_mm2"] == answer["material"]["us_n_mm2"]
    rest.delete_session(sid)


def test_values_fitted_elsewhere_are_applied_with_their_provenance(rest):
    s = rest.create_session("phantom:layered", voxel_mm=VOXEL_MM)
    sid = s["id"]
    answer = rest.apply_calibration(sid, label=2, us_n_mm2=300.0,
                                    provenance={"us_ci": [280.0, 320.0], "source": "lab 3"})
    materials = {m["label"]: m for m in rest.materials(sid)}
    assert materials[2]["us_n_mm2"] == 300.0 and materials[2]["k"] == answer["material"]["k"]
    record = rest.calibrations(sid)["2"]
    assert record["provenance"] == {"us_ci": [280.0, 320.0], "source": "lab 3"}
    assert record["fit"] is None and record["in_force"] is True
    rest.set_material(sid, 2, us_n_mm2=310.0)  # set another way: the record says so
    record = rest.calibrations(sid)["2"]
    assert record["in_force"] is False and record["current"]["us_n_mm2"] == 310.0
    assert record["us_n_mm2"] == 300.0
    rest.apply_calibration(sid, label=2, us_n_mm2=300.0, provenance={"n_rows": 45})
    assert rest.calibrations(sid)["2"]["provenance"] == {"n_rows": 45}  # an int stays one
    rest.delete_session(sid)


def test_bad_calibrations_are_refused_and_change_nothing(stack, rest):
    s = rest.create_session("phantom:workpiece", voxel_mm=VOXEL_MM)
    sid = s["id"]
    cases = _table(805.1, 1.3)
    on_workpiece = [{**c, "feed_N": -c["feed_N"], "lateral_N": -c["lateral_N"],
                     "normal_N": -c["normal_N"]} for c in cases]
    # Normal forces that pull the burr in: the best K is negative.
    negative_k = [{**c, "normal_N": -c["normal_N"]} for c in cases]
    refusals = [
        ({"us_n_mm2": 900.0, "fit": {"cases": cases}}, 422, "not both"),
        ({}, 422, "either fit"),
        ({"fit": {"cases": on_workpiece}}, 422, "ON THE BURR"),
        ({"fit": {"cases": cases}, "k": 1.0}, 422, "k goes inside fit"),
        ({"us_n_mm2": 900.0, "label": 9}, 404, "no material with label 9"),
        ({"us_n_mm2": -5.0}, 422, "greater than 0"),
        ({"us_n_mm2": 0.0}, 422, "greater than 0"),
        ({"fit": {"cases": negative_k}}, 422, "outside [0, 100]"),
        ({"fit": {"cases": [{**cases[0], "orientation": "sideways"}] * 3}}, 422, "orientation"),
        ({"fit": {"cases": cases, "components": ["feed", "feed"]}}, 422, "distinct"),
    ]
    with httpx.Client(base_url=stack.url + "/v1", timeout=60.0,
                      headers={"Authorization": f"Bearer {TOKEN}"}) as api:
        for body, status, message in refusals:
            r = api.post(f"/sessions/{sid}/calibration", json=body)
            assert r.status_code == status, (body.keys(), r.text)
            assert message in r.text, r.text
        assert api.post("/sessions/999/calibration",
                        json={"us_n_mm2": 900.0}).status_code == 404
    assert rest.materials(sid)[0]["us_n_mm2"] == 805.1
    assert rest.calibrations(sid) == {}
    with pytest.raises(RestError):
        rest.fit_calibration(cases[:1])
    rest.delete_session(sid)


def test_the_cli_applies_its_fit_to_the_local_server(stack, rest, tmp_path, monkeypatch,
                                                     capsys):
    s = rest.create_session("phantom:workpiece", voxel_mm=VOXEL_MM)
    conn = write_connection(Connection(*stack.udp_address, s["id"], s["key"], "model",
                                       VOXEL_MM, stack.url, TOKEN), tmp_path / "conn.json")
    monkeypatch.setenv("BURRFORCE_CONNECTION", str(conn))
    rows = [CaseRow(c, *(m * 1.5).tolist()) for c, m in zip(
        thesis_cases(), Sensitivities().predict(list(thesis_cases()), 805.1, 1.3), strict=True)]
    table = write_case_table(tmp_path / "cases.csv", rows)
    assert main(["calibrate", "--cases", str(table), "--fit", "us,k", "--apply",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["applied"]["material"]["us_n_mm2"] == pytest.approx(1.5 * 805.1, rel=1e-6)
    record = rest.calibrations(s["id"])["1"]
    assert record["provenance"]["n_rows"] == 9 and record["k"] == pytest.approx(1.3, rel=1e-6)
    rest.delete_session(s["id"])
