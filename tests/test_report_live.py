"""A live session's report (``GET /v1/sessions/ID/report``) against a real server: a client
streams a groove over UDP through the layered block into its trabecular core (made
forbidden), the control plane samples the session's telemetry at 100 Hz (``api.history``),
and the report combines that history with the engine's own removed volume and forbidden
contacts."""

from __future__ import annotations

import json
import time

import httpx
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from waiting import wait_until

from burrforce.client.rest import BurrRest, RestError
from burrforce.client.udp import BurrClient, ServerGone
from burrforce.proto.messages import STATUS_CUTTING
from burrforce.server.api import history
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.models import Features, Parameters
from burrforce.server.api.stack import ServerStack
from burrforce.server.bone.phantoms import TRABECULAR_LABEL

TOKEN = "live-report-test-token-0123456789"
SID = 5
CSP = "default-src 'none'; style-src 'unsafe-inline'; img-src data:"


def _stream(stack, sid: int, points, forces: list[float] | None = None,
            sent_s: list[float] | None = None) -> None:
    """One exchange per point (engine frame, mm) at 60 000 rpm; |force| of each reply got,
    and the monotonic time each packet went out (s)."""
    session = stack.plane.get(sid)
    with BurrClient(*stack.udp_address, session.id, session.key_hex) as client:
        for p in points:
            if sent_s is not None:
                sent_s.append(time.monotonic())
            try:
                reply = client.exchange(tuple(p), rpm=60000.0, timeout_s=0.5).reply
            except (TimeoutError, ServerGone):
                continue
            if forces is not None:
                forces.append(float(np.linalg.norm(reply.force)))
            time.sleep(0.0005)


def _caught_up(stack, sid: int) -> bool:
    """The history holds the latest packet the telemetry shows."""
    sample = stack.plane.telemetry.sample(sid, ticks=False)
    view = stack.plane.history.view(sid)
    return sample is not None and len(view.t_s) > 0 and view.t_s[-1] == sample.t_recv_s


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with ServerStack(ServeConfig(http_port=0, udp_port=0,
                                 data_dir=tmp_path_factory.mktemp("live")), TOKEN,
                     journal=False) as st_:
        yield st_


@pytest.fixture(scope="module")
def streamed(stack):
    """A shallow groove in the cortical shell, then a deep one into the forbidden core."""
    source = stack.plane.resolve("phantom:layered", None, 0.25)
    stack.add_session(source, Parameters(), session_id=SID)
    stack.plane.set_material(SID, TRABECULAR_LABEL, None, {"forbidden": True})
    forces: list[float] = []
    sent_s: list[float] = []
    # The burr (2 mm) 1 mm into the 1.5 mm shell, then 3 mm down: into the core.
    shallow = [(2.0 + 0.01 * i, 0.0, 1.0) for i in range(300)]
    deep = [(2.0 + 0.01 * i, 4.0, -1.0) for i in range(300)]
    _stream(stack, SID, shallow + deep, forces, sent_s)
    assert wait_until(lambda: _caught_up(stack, SID))
    return {"forces": forces, "first_sent_s": sent_s[0], "deep_sent_s": sent_s[len(shallow)]}


def _api(stack) -> httpx.Client:
    return httpx.Client(base_url=stack.url + "/v1", timeout=60.0,
                        headers={"Authorization": f"Bearer {TOKEN}"})


def test_the_report_is_the_engines_volumes_and_the_sampled_forces(stack, streamed):
    with _api(stack) as api:
        r = api.get(f"/sessions/{SID}/report")
        assert r.status_code == 200, r.text
        report = r.json()
        state = api.get(f"/sessions/{SID}/state", params={"max_events": 10_000}).json()
    assert report["source"] == f"session {SID}" and report["source_kind"] == "session"
    assert report["session_id"] == SID and report["complete"] is True
    removed = report["removed_mm3_by_material"]
    assert set(removed) == {"cortical", "trabecular"}
    assert removed == pytest.approx(state["removed_mm3"], rel=1e-12)
    assert report["removed_mm3"] == pytest.approx(sum(state["removed_mm3"].values()))
    assert 0.0 < report["cutting_s"] <= report["duration_s"]
    assert 0.0 < report["contact_s"] <= report["duration_s"]
    assert report["ticks"] >= 20  # 100 Hz over a stream of about a second
    # The sampled peak is one of the replies' forces (stored as float32), and the grooves'
    # steady force is sampled many times: it is at least the median reply's.
    forces = np.array(streamed["forces"])
    peak = report["hand_force_peak_N"]
    assert np.min(np.abs(forces - peak)) <= 1e-6 * peak
    assert np.median(forces) <= peak <= forces.max() * (1 + 1e-6)
    assert report["notes"][0] == ("hand force and cutting time sampled at 100 Hz from live "
                                  "telemetry; a 1 kHz stream's ticks between samples are "
                                  "not seen")
    # The deep groove entered the forbidden core: events on the report's time base.
    contacts = report["forbidden_contacts"]
    assert len(contacts) == len(state["events"]) >= 1
    assert contacts[0]["material"] == "trabecular"
    first = state["events"][0]
    assert contacts[0]["position_mm"] == pytest.approx(first["position_mm"])
    # In the deep groove: after the shallow one. Both clocks are this machine's monotonic
    # one. The report counts from its first 100 Hz sample, never before the stream began;
    # on a busy machine the sampler starts late, so that base is not the stream's start.
    assert first["time_s"] >= streamed["deep_sent_s"]
    t0_s = first["time_s"] - contacts[0]["time_s"]
    assert streamed["first_sent_s"] - 2 / stack.plane.history.hz <= t0_s
    assert 0.0 < contacts[0]["time_s"] <= report["duration_s"]
    assert report["started_at"] and "T" in report["started_at"]


def test_html_threshold_and_errors(stack, streamed):
    with _api(stack) as api:
        r = api.get(f"/sessions/{SID}/report", params={"format": "html", "threshold_n": 0.5})
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert r.headers["content-security-policy"] == CSP
        assert "<svg" in r.text and "Time above 0.5 N" in r.text and "trabecular" in r.text
        assert "<script" not in r.text
        assert httpx.get(f"{stack.url}/v1/sessions/{SID}/report").status_code == 401
        assert api.get("/sessions/99/report").status_code == 404
        for bad in ("0", "-1", "nan", "inf", "lots", "1.7976931348623157e+308"):
            r = api.get(f"/sessions/{SID}/report", params={"threshold_n": bad})
            assert r.status_code == 422, (bad, r.text)
        assert api.get(f"/sessions/{SID}/report", params={"format": "pdf"}).status_code == 422


def test_the_rest_client_gets_it(stack, streamed):
    with BurrRest(stack.url, TOKEN) as api:
        report = api.session_report(SID, threshold_n=0.5)
        assert report["threshold_N"] == 0.5 and report["source_kind"] == "session"
        page = api.session_report(SID, format="html")
        assert page.startswith("<!DOCTYPE html>") and "<svg" in page
        with pytest.raises(RestError) as missing:
            api.session_report(99)
        assert missing.value.status == 404


def test_a_deleted_sessions_history_goes_and_a_new_one_starts_afresh(stack):
    source = stack.plane.resolve("phantom:workpiece", None, 0.5)
    stack.add_session(source, Parameters(), session_id=9)
    try:
        _stream(stack, 9, [(0.01 * i, 0.0, -0.5) for i in range(40)])
        assert wait_until(lambda: _caught_up(stack, 9))
        before = len(stack.plane.history.view(9).t_s)
        assert before >= 1
    finally:
        stack.plane.delete_session(9)
    assert len(stack.plane.history.view(9).t_s) == 0
    stack.add_session(source, Parameters(), session_id=9)
    try:
        time.sleep(0.1)  # a few sampler passes: an idle new session adds no row
        assert len(stack.plane.history.view(9).t_s) == 0
        with BurrRest(stack.url, TOKEN) as api:
            empty = api.session_report(9)
        assert empty["ticks"] == 0 and empty["duration_s"] == 0.0
        assert empty["removed_mm3"] == 0.0
        assert json.loads(json.dumps(empty)) == empty
    finally:
        stack.plane.delete_session(9)


@given(st.integers(0, 40), st.integers(1, 12), st.integers(1, 5))
def test_the_ring_keeps_the_newest_rows_in_order(n, max_rows, chunk):
    """Grown in chunks up to its bound, then the oldest rows go first."""
    track = history._Track(None, max_rows, chunk)  # type: ignore[arg-type]
    for i in range(n):
        track.append(float(i), float(i), i % 7, 1)
    rows = track.ordered()
    assert len(track.rows) <= max_rows and track.dropped == max(n - max_rows, 0)
    kept = list(range(max(n - max_rows, 0), n))
    assert rows["t_s"].tolist() == [float(i) for i in kept]
    assert rows["status"].tolist() == [i % 7 for i in kept]


def test_cutting_status_is_kept(stack, streamed):
    view = stack.plane.history.view(SID)
    assert (view.status & STATUS_CUTTING).any()
    assert np.all(np.diff(view.t_s) >= 0.0)


def test_a_coupled_sessions_report_has_its_cutting_time(stack):
    """The coupled output builds its replies in Python, which keeps them where the raw
    kernel keeps its own: the history sees their status bits like the raw output's."""
    source = stack.plane.resolve("phantom:workpiece", None, 0.25)
    stack.add_session(source, Parameters(device="generic"), Features(coupling=True),
                      session_id=11)
    try:
        _stream(stack, 11, [(1.0 + 0.01 * i, 0.0, 1.0) for i in range(300)])
        sample = stack.plane.telemetry.sample(11, ticks=False)
        assert sample.reply_current and sample.seq is not None
        time.sleep(0.05)  # a few sampler passes after the last packet (not asserted on)
        with BurrRest(stack.url, TOKEN) as api:
            report = api.session_report(11)
            state = api.state(11)
        assert report["removed_mm3"] == pytest.approx(sum(state["removed_mm3"].values()))
        assert report["removed_mm3"] > 0.0
        assert 0.0 < report["cutting_s"] <= report["duration_s"]
        assert report["hand_force_peak_N"] > 0.0
    finally:
        stack.plane.delete_session(11)
