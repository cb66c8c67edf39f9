"""Session reports (``burrforce report``, ``GET /v1/recordings/NAME/report``) of real
recordings: a session cutting through a layered block into a forbidden core, recorded, then
reported from its rows and a replay."""

from __future__ import annotations

import json
import math
import shutil
from html.parser import HTMLParser
from pathlib import Path

import httpx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.client.rest import BurrRest, RestError
from burrforce.proto.codec import decode_server_message
from burrforce.proto.messages import OK, STATUS_CUTTING, Pose, Reply
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack
from burrforce.server.bone import BoneEngine
from burrforce.server.bone.phantoms import TRABECULAR_LABEL, phantom
from burrforce.server.cli import main
from burrforce.server.haptics.config import HapticsConfig
from burrforce.server.hotloop import Session, SessionConfig
from burrforce.server.record import read_recording, replay, start_recording
from burrforce.server.report import (
    SessionReport,
    downsample_min_max,
    render_html,
    report_from_recording,
)
from burrforce.server.report.series import MAX_TICK_S

T0_NS = 10**12
TOKEN = "test-token-report-0123456789"
HOSTILE = '<b onmouseover="alert(1)">x&y<i>'


def tilted(alpha_deg: float = 60.0) -> tuple[float, float, float, float]:
    """Quaternion taking +z to the thesis's tool axis (−cos α, 0, sin α)."""
    beta = math.radians(alpha_deg - 90.0)
    return (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))


class Driver:
    """Feeds a session poses at 1 kHz, as the dispatcher would; ``pause`` leaves a silence."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self.seq = 0
        self.t_us = 0

    def tick(self, position, rpm: float = 60_000.0) -> Reply:
        self.seq += 1
        self.t_us += 1000
        pose = Pose(1, self.seq, self.t_us, tuple(position), tilted(), rpm, True, None, 0)
        assert self.session.admit(pose.seq) == OK
        data, error = self.session.respond(pose, T0_NS + self.t_us * 1000)
        assert error == OK
        reply = decode_server_message(data)
        assert isinstance(reply, Reply)
        return reply

    def groove(self, n: int, depth_mm: float, x0: float = 2.0, feed_mm_s: float = 20.0,
               **kw) -> list[Reply]:
        return [self.tick((x0 + feed_mm_s * (i + 1) * 1e-3, 0.0, 2.0 - depth_mm), **kw)
                for i in range(n)]

    def pause(self, seconds: float) -> None:
        self.t_us += round(seconds * 1e6)


def _session(haptics: HapticsConfig | None = None) -> Session:
    bone = phantom("layered", 0.25)
    config = SessionConfig(haptics=haptics) if haptics else SessionConfig()
    session = Session(1, BoneEngine(bone.grid, bone.materials), config)
    session.engine.materials.update(TRABECULAR_LABEL, forbidden=True)
    return session


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A shallow groove in the cortex, a 0.3 s silence, then a deep one into the forbidden
    trabecular core, and a slow spindle touching without cutting."""
    session = _session()
    recorder = start_recording(session, tmp_path_factory.mktemp("rec") / "trainee",
                               chunk_rows=128)
    driver = Driver(session)
    replies = driver.groove(120, 0.5)
    driver.pause(0.3)
    replies += driver.groove(200, 2.2, x0=4.5)
    replies += driver.groove(30, 0.5, x0=9.0, rpm=1000.0)
    recorder.close()
    return {"path": recorder.path, "session": session, "replies": replies}


@pytest.fixture(scope="module")
def report(recorded) -> SessionReport:
    return report_from_recording(recorded["path"])


def _direct(rec) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(tick durations, |recorded force|, status) straight from the rows."""
    rows = rec.rows
    t = (rows["t_recv_ns"] - rows["t_recv_ns"][0]) * 1e-9
    step = np.diff(t)
    dt = np.append(np.where(step <= MAX_TICK_S, step, min(np.median(step), MAX_TICK_S)), 0.0)
    force = np.linalg.norm(rows["force"], axis=1)
    return dt, force, rows["status"]


# -- the report -------------------------------------------------------------------------------
def test_volumes_and_forbidden_contacts_are_the_replays(recorded, report):
    replayed = replay(recorded["path"])
    assert replayed.reproduced
    assert report.removed_mm3_by_material == replayed.removed_mm3_by_material
    assert set(report.removed_mm3_by_material) == {"cortical", "trabecular"}
    assert report.removed_mm3 == pytest.approx(replayed.removed_mm3, rel=1e-12)
    assert report.removed_mm3_by_material == recorded["session"].engine.removed_mm3_by_material()
    events = replayed.forbidden_events
    assert len(report.forbidden_contacts) == len(events) >= 1
    for c, e in zip(report.forbidden_contacts, events, strict=True):
        assert (c.time_s, c.label, c.material, list(c.position_mm)) \
            == (e["t_s"], e["label"], e["material"], e["position_mm"])
    assert report.forbidden_contacts[0].material == "trabecular"
    # It began in the deep groove: after the shallow one and the silence.
    assert report.forbidden_contacts[0].time_s > 0.119 + 0.3
    assert report.source == "trainee.burrrec" and report.session_id == 1
    assert report.started_at and "T" in report.started_at
    assert report.complete and report.notes == []


def test_times_and_hand_force_are_the_recorded_replies(recorded, report):
    rec = read_recording(recorded["path"])
    dt, force, status = _direct(rec)
    cutting = (status & STATUS_CUTTING) != 0
    assert report.ticks == len(recorded["replies"])
    assert report.duration_s == pytest.approx(349 * 1e-3 + 0.3)
    assert report.cutting_s == pytest.approx(dt[cutting].sum(), rel=1e-12)
    # The silence counts as one tick (1 ms), not 0.3 s.
    assert 0.3 < report.cutting_s <= 0.321
    assert report.contact_s > report.cutting_s  # the slow spindle touches without cutting
    assert report.hand_force_peak_N == force.max() > 0.0
    threshold = float(np.median(force[cutting]))
    r = report_from_recording(rec, threshold_N=threshold)
    assert r.threshold_N == threshold
    assert r.time_above_threshold_s == pytest.approx(dt[force > threshold].sum(), rel=1e-12)
    assert 0.0 < r.time_above_threshold_s < r.cutting_s


def test_a_coupled_session_reports_the_force_the_hand_was_sent(tmp_path):
    session = _session(HapticsConfig(output="coupled"))
    recorder = start_recording(session, tmp_path / "coupled", chunk_rows=128)
    replies = Driver(session).groove(150, 1.0)
    recorder.close()
    sent = np.array([np.linalg.norm(r.force) for r in replies])
    replayed = replay(recorder.path)
    assert not np.allclose(replayed.force_N, sent)  # the raw cut, not what the hand felt
    r = report_from_recording(recorder.path)
    # The same vectors, their norm taken two ways (numpy's norm, the report's root of the
    # sum of squares): equal to the last bit or two, not always bit for bit.
    assert r.hand_force_peak_N == pytest.approx(sent.max(), rel=1e-14)
    assert r.time_above_threshold_s == pytest.approx(
        1e-3 * np.count_nonzero(sent[:-1] > r.threshold_N))


def test_the_series_keeps_the_peak_and_is_plot_sized(report):
    assert len(report.series_t_s) == report.ticks <= 2000  # short: kept whole
    assert report.series_force_N.max() == report.hand_force_peak_N
    assert report.cutting_intervals_s and all(a < b for a, b in report.cutting_intervals_s)


def test_json_is_strict_and_complete(report):
    d = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert d["removed_mm3_by_material"] == report.removed_mm3_by_material
    assert len(d["forbidden_contacts"]) == len(report.forbidden_contacts)
    assert set(d["forbidden_contacts"][0]) == {"time_s", "label", "material", "position_mm"}
    assert len(d["series"]["t_s"]) == len(d["series"]["force_N"])


# -- HTML -------------------------------------------------------------------------------------
class _Collect(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[str] = []
        self.text: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)

    def handle_data(self, data):
        self.text.append(data)


def _check_page(page: str) -> _Collect:
    parser = _Collect()
    parser.feed(page)
    parser.close()
    low = page.lower()
    assert "<script" not in low and "http://" not in low and "https://" not in low
    assert "src=" not in low and "href=" not in low  # nothing to load
    assert {"html", "style", "table", "svg", "polyline"} <= set(parser.tags)
    return parser


def test_the_page_is_self_contained_and_in_reading_order(report):
    page = render_html(report)
    parser = _check_page(page)
    text = " ".join(parser.text)
    assert "Forbidden contacts" in text and "trabecular" in text
    assert page.index("Peak hand force") < page.index("<h2>Forbidden contacts") \
        < page.index("<svg")


def test_a_hostile_recording_name_is_escaped(recorded, tmp_path):
    hostile = Path(shutil.copytree(recorded["path"], tmp_path / (HOSTILE + ".burrrec")))
    page = render_html(report_from_recording(hostile))
    _check_page(page)
    assert HOSTILE not in page and "<b " not in page
    assert "&lt;b onmouseover=&quot;alert(1)&quot;&gt;x&amp;y" in page


# -- the command ------------------------------------------------------------------------------
def test_cli_text_json_and_html(recorded, report, tmp_path, capsys):
    path = str(recorded["path"])
    assert main(["report", path]) == 0
    out = capsys.readouterr().out
    assert "forbidden contacts: " in out and "trabecular" in out
    page = tmp_path / "r.html"
    assert main(["report", path, "--json", "--html", str(page), "--threshold-n", "1.5"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d == json.loads(json.dumps(report_from_recording(path, 1.5).to_dict()))
    assert d["threshold_N"] == 1.5 and d["removed_mm3"] == report.removed_mm3
    _check_page(page.read_text(encoding="utf-8"))


@pytest.mark.skipif(shutil.which("script") is None, reason="needs util-linux's script (a pty)")
def test_on_a_terminal_the_report_prints_each_line_once(recorded):
    """On a terminal the replay draws a bar on stderr; the report itself must come out once
    (a first run once showed its last lines twice)."""
    import re
    import subprocess
    import sys

    command = f"stty cols 100; {sys.executable} -m burrforce.server.cli report " \
              f"'{recorded['path']}'"
    out = subprocess.run(["script", "-qec", command, "/dev/null"], capture_output=True,
                         text=True, timeout=300, stdin=subprocess.DEVNULL)
    assert out.returncode == 0, out.stdout + out.stderr
    screen = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.stdout)
    lines = [line.strip() for part in screen.split("\n") for line in part.split("\r")]
    report = report_from_recording(recorded["path"]).format_text().splitlines()
    for line in report:
        assert lines.count(line.strip()) == 1, (line, screen)


def test_cli_bad_input_is_exit_2_without_a_traceback(tmp_path, capsys):
    (tmp_path / "plain.txt").write_text("x")
    for bad in (tmp_path / "missing.burrrec", tmp_path / "plain.txt", tmp_path):
        assert main(["report", str(bad)]) == 2
        err = capsys.readouterr().err
        assert "burrforce report: error:" in err and "Traceback" not in err
    for bad in ("0", "1e308"):
        with pytest.raises(SystemExit):
            main(["report", str(tmp_path), "--threshold-n", bad])


# -- REST -------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stack(tmp_path_factory, recorded):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path_factory.mktemp("data"))
    with ServerStack(config, TOKEN) as s:
        shutil.copytree(recorded["path"], s.plane.recordings_dir / "trainee.burrrec")
        yield s


def test_rest_report_json_and_html(stack, report):
    auth = {"Authorization": f"Bearer {TOKEN}"}
    with httpx.Client(base_url=stack.url + "/v1", timeout=60.0) as api:
        r = api.get("/recordings/trainee/report", headers=auth)
        assert r.status_code == 200, r.text
        assert r.json() == json.loads(json.dumps(report.to_dict()))
        r = api.get("/recordings/trainee.burrrec/report",
                    params={"format": "html", "threshold_n": 0.5}, headers=auth)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert r.headers["content-security-policy"] \
            == "default-src 'none'; style-src 'unsafe-inline'; img-src data:"
        _check_page(r.text)
        assert "Time above 0.5 N" in r.text
        assert api.get("/recordings/trainee/report").status_code == 401
        assert api.get("/recordings/nobody/report", headers=auth).status_code == 404
        for bad in ("0", "-1", "nan", "inf", "lots", "1.7976931348623157e+308"):
            r = api.get("/recordings/trainee/report", params={"threshold_n": bad},
                        headers=auth)
            assert r.status_code == 422, (bad, r.text)
        r = api.get("/recordings/trainee/report", params={"format": "pdf"}, headers=auth)
        assert r.status_code == 422


def test_rest_client_gets_the_report(stack, report, tmp_path):
    with BurrRest(stack.url, TOKEN) as api:
        assert api.recording_report("trainee") == json.loads(json.dumps(report.to_dict()))
        assert api.recording_report("trainee", threshold_n=0.5)["threshold_N"] == 0.5
        page = api.download_recording_report("trainee", tmp_path / "r.html")
        _check_page(page.read_text(encoding="utf-8"))
        with pytest.raises(RestError) as missing:
            api.recording_report("nobody")
        assert missing.value.status == 404


# -- the downsampler --------------------------------------------------------------------------
@given(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=3000),
       st.integers(2, 600))
def test_downsampling_keeps_the_extremes_in_time_order(values, limit):
    y = np.array(values)
    t = np.cumsum(np.full(len(y), 1e-3))
    ts, ys = downsample_min_max(t, y, limit)
    assert len(ts) == len(ys) <= limit
    assert ys.max() == y.max() and ys.min() == y.min()
    assert np.all(np.diff(ts) > 0.0)
    # Every kept point is a point of the series.
    np.testing.assert_array_equal(ys, y[np.searchsorted(t, ts)])


def test_a_long_session_from_ticks_keeps_its_peak_and_merges_close_cutting_runs():
    """The path a live session would take: per-tick arrays straight into the report."""
    n = 20_000
    t = np.arange(n) * 1e-3
    force = np.full(n, 1.0)
    force[12_345] = 9.0  # a 1 ms spike
    status = np.zeros(n, dtype=np.uint16)
    status[1000:5000] = STATUS_CUTTING
    status[5001:6000] = STATUS_CUTTING  # a 1 ms break: one run on a 20 s plot
    status[9000:9100] = STATUS_CUTTING
    r = SessionReport.from_ticks(source="session 3", source_kind="session", t_s=t,
                                 status=status, hand_force_N=force,
                                 removed_mm3_by_material={"cortical": 1.5},
                                 forbidden_contacts=[], threshold_N=5.0)
    assert len(r.series_t_s) <= 2000 and r.series_force_N.max() == 9.0
    assert r.time_above_threshold_s == pytest.approx(1e-3)
    assert r.cutting_s == pytest.approx(5.099)
    assert r.cutting_intervals_s == [pytest.approx((1.0, 6.0)), pytest.approx((9.0, 9.1))]
    assert r.hand_force_mean_N == 1.0 and r.contact_s == r.cutting_s  # the spike: no contact
    with pytest.raises(ValueError, match="threshold"):
        SessionReport.from_ticks(source="s", source_kind="session", t_s=t, status=status,
                                 hand_force_N=force, removed_mm3_by_material={},
                                 forbidden_contacts=[], threshold_N=float("nan"))


@given(threshold=st.floats(0.0, 1e4), peak=st.floats(0.0, 1e4), n=st.integers(0, 50))
def test_the_force_plot_draws_for_any_threshold_and_force(threshold, peak, n):
    """A threshold of 5e-324 N with no force made the axis step underflow to 0 and the report
    answer 500 (schemathesis); every valid threshold and force now gives an axis above both."""
    from burrforce.server.report.svg import force_plot

    t = np.linspace(0.0, 1.0, n)
    f = np.linspace(0.0, peak, n)
    svg = force_plot(t, f, threshold, [0.5], [(0.1, 0.2)])
    assert svg.startswith("<svg") and svg.endswith("</svg>")
