"""A failed hot-loop command reaches the REST caller with the status of its kind and the hot
loop's own message: invalid → 422, not_found → 404, conflict → 409, unavailable → 503, through
the real stack (hot-loop processes, the control plane, uvicorn on 127.0.0.1, httpx). Each
failure is provoked for real, by giving the loop a state the control plane does not know of;
``internal`` cannot be provoked through REST (every command's bad input is caught before), so
its mapping is checked where it is made, ``api.errors``."""

from __future__ import annotations

import os
import signal
import time

import httpx
import pytest

from burrforce.server.api import errors
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.stack import ServerStack
from burrforce.server.hotloop import SessionSpec
from burrforce.server.hotloop.errors import KINDS, CommandError
from burrforce.server.hotloop.handle import START_TIMEOUT_S

TOKEN = "test-token-errors-0123456789"
VOXEL_MM = 0.5
BONE = {"source": "phantom:workpiece", "voxel_mm": VOXEL_MM}


def _serve(tmp_path):
    return ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path / "data"),
                       TOKEN, journal=False)


def _client(stack) -> httpx.Client:
    return httpx.Client(base_url=stack.url + "/v1", timeout=600.0,
                        headers={"Authorization": f"Bearer {TOKEN}"})


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with _serve(tmp_path_factory.mktemp("errors")) as s:
        yield s


@pytest.fixture(scope="module")
def api(stack):
    with _client(stack) as client:
        yield client


def _session(api, **body) -> dict:
    r = api.post("/sessions", json={"bone": BONE, **body})
    assert r.status_code == 201, r.text
    return r.json()


def _detail(r: httpx.Response) -> str:
    detail = r.json()["detail"]
    return detail[0]["msg"] if isinstance(detail, list) else detail


def test_invalid_is_422_with_the_loops_message(stack, api, tmp_path):
    # The loop records the session already (started behind the control plane's back): the
    # loop refuses a second recorder as bad arguments. The first recording in a fresh loop
    # may compile its kernels: the long timeout.
    sid = _session(api)["id"]
    stack.hot.call("start_recording", timeout_s=START_TIMEOUT_S, session_id=sid,
                   path=str(tmp_path / "direct.burrrec"), snapshot_version=None)
    try:
        r = api.post(f"/sessions/{sid}/recording", json={"name": "refused"})
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["type"] == "value_error"
        assert _detail(r) == f"session {sid} is already being recorded"
        # Nothing of the refused recording is left.
        assert "refused.burrrec" not in [x["name"] for x in api.get("/recordings").json()]
    finally:
        stack.hot.call("stop_recording", session_id=sid)
        api.delete(f"/sessions/{sid}")


def test_not_found_is_404_with_the_loops_message(stack, api):
    # The loop lost the session the control plane still has.
    sid = _session(api)["id"]
    assert stack.hot.call("remove_session", session_id=sid) is True
    try:
        r = api.get(f"/sessions/{sid}/state")
        assert r.status_code == 404, r.text
        assert _detail(r) == f"no session {sid}"
    finally:
        api.delete(f"/sessions/{sid}")


def test_conflict_is_409_with_the_loops_message(stack, api):
    # The loop serves an id the control plane has not given out: the new session's load is
    # refused by the loop, and the answer says so.
    sid = 4242
    stack.hot.call("add_session", spec=SessionSpec(sid, "phantom:workpiece", VOXEL_MM, None))
    try:
        r = api.post("/sessions", json={"id": sid, "bone": BONE})
        assert r.status_code == 409, r.text
        assert _detail(r).endswith(f"session {sid} exists")
        assert api.get(f"/sessions/{sid}").status_code == 404  # not kept half made
    finally:
        stack.hot.call("remove_session", session_id=sid)


def test_unavailable_is_503_with_the_loops_message(tmp_path):
    with _serve(tmp_path) as stack, _client(stack) as api:
        sid = _session(api)["id"]
        stack.supervisor.stop()  # no restart: the window in which the loop is gone
        hot = stack.hot
        os.kill(hot.pid, signal.SIGKILL)
        deadline = time.monotonic() + 30.0
        while hot.is_alive():
            assert time.monotonic() < deadline
            time.sleep(0.02)
        r = api.get(f"/sessions/{sid}/state")
        assert r.status_code == 503, r.text
        assert _detail(r).startswith("the hot loop cannot do it: ")
        with pytest.raises(CommandError) as err:  # what the loop's handle said
            hot.call("session_state", session_id=sid)
        assert err.value.kind == "unavailable"
        assert _detail(r) == f"the hot loop cannot do it: {err.value.message}"


@pytest.mark.parametrize(("kind", "status", "as_is"), [
    ("invalid", 422, True), ("not_found", 404, True), ("conflict", 409, True),
    ("no_room", 507, True), ("unavailable", 503, False), ("internal", 503, False),
])
def test_each_kind_maps_to_one_error_and_status(kind, status, as_is):
    error = errors.from_command(CommandError(kind, "what the loop said"))
    assert isinstance(error, errors.COMMAND_ERRORS[kind])
    assert errors.http_status(error) == error.status == status
    assert error.detail == ("what the loop said" if as_is
                            else "the hot loop cannot do it: what the loop said")


def test_every_kind_and_every_domain_error_has_a_status():
    assert set(errors.COMMAND_ERRORS) == set(KINDS)
    for cls in errors.HTTP_STATUS:
        assert 400 <= errors.http_status(cls) < 600
    assert errors.http_status(errors.ApiError("no kind")) == 500


def test_a_misspelled_parameter_gets_the_closest_valid_name(api):
    sid = _session(api)["id"]
    try:
        r = api.patch(f"/sessions/{sid}/parameters", json={"Us": 900})
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "Us"]
        assert "did you mean `us_n_mm2`?" in _detail(r)
        r = api.patch(f"/sessions/{sid}/parameters", json={"radius_m": 1.0})
        assert "did you mean `radius_mm`?" in _detail(r)
        # Nothing close: pydantic's message alone.
        r = api.patch(f"/sessions/{sid}/parameters", json={"zzzz": 1})
        assert r.status_code == 422 and "did you mean" not in _detail(r)
    finally:
        api.delete(f"/sessions/{sid}")


def test_a_body_not_sent_as_json_gets_a_hint_about_the_header(api):
    sid = _session(api)["id"]
    try:
        r = api.patch(f"/sessions/{sid}/parameters", content=b'{"us_n_mm2": 900}',
                      headers={"Content-Type": "text/plain"})
        assert r.status_code == 422, r.text
        assert "Content-Type: application/json" in _detail(r)
        # Sent as JSON, the same body is taken.
        r = api.patch(f"/sessions/{sid}/parameters", json={"us_n_mm2": 900})
        assert r.status_code == 200, r.text
    finally:
        api.delete(f"/sessions/{sid}")


def test_a_401_says_where_the_token_is(stack):
    r = httpx.get(stack.url + "/v1/sessions", timeout=30.0)
    assert r.status_code == 401
    detail = r.json()["detail"]
    assert str(stack.config.data_dir / "token") in detail
    r = httpx.get(stack.url + "/v1/sessions", timeout=30.0,
                  headers={"Authorization": "Bearer wrong"})
    assert r.status_code == 401 and str(stack.config.data_dir / "token") in r.json()["detail"]
