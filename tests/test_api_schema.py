"""The REST API against its own OpenAPI schema, live: schemathesis generates valid and invalid
requests for every operation and sends them to a real server (hot loop process + control
plane + uvicorn on 127.0.0.1). No answer may be a 5xx, every answer must match the schema the
API publishes, and no setting the API accepts may break the hot loop (a datagram after each
accepted change must be answered). Bounded: EXAMPLES_PER_OPERATION per operation."""

from __future__ import annotations

import json

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, reject, settings
from hypothesis_profiles import examples
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import response_schema_conformance
from test_rest_client import live_server  # the shared live server (see that module)

from burrforce.client import BurrClient, ServerError
from burrforce.proto.messages import ERROR_NAMES

EXAMPLES_PER_OPERATION = examples(25)
#: Most generated session ids are sent to the fixture session (a random id is a 404 and
#: tests nothing past the lookup); one in FIXTURE_SHARE keeps its random id.
FIXTURE_SHARE = 4
#: Accepted requests of these methods on a session change what the hot loop does for it:
#: each is followed by a datagram.
CHANGES = ("PUT", "PATCH", "POST", "DELETE")


def _published_schema() -> dict:
    """The OpenAPI document the app publishes, built without a server (create_app reads only
    the plane's configuration while it builds the routes);
    test_the_live_server_publishes_this_schema checks the live one is the same."""
    from types import SimpleNamespace

    from burrforce.server.api.app import create_app
    from burrforce.server.api.config import ServeConfig
    from burrforce.server.api.metrics import LoopStats

    app = create_app(SimpleNamespace(config=ServeConfig()), "t" * 16,  # type: ignore[arg-type]
                     LoopStats(lambda since: {}))
    return app.openapi()


PUBLISHED = _published_schema()
# schemathesis.pytest.from_fixture (the schema loaded from the live server when the test
# runs) fails on pytest 9: its lazy loader reads and sets Function._nodeid, which pytest 9
# no longer has. So the schema is built at collection and each call is sent to the live URL.
# Attaching a device starts a device-loop process per example and streams into the fixture
# session like a second engine (the loop probe's datagrams would then be stale): its bodies
# and answers are tested in test_devices_loop.py instead.
schema = schemathesis.openapi.from_dict(PUBLISHED).exclude(
    method="PUT", path="/v1/sessions/{session_id}/device")


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with live_server(tmp_path_factory.mktemp("api-schema")) as server:
        yield server


@pytest.fixture(scope="module")
def loop_probe(live):
    """A UDP client of the fixture session: one datagram tells whether the loop still
    computes it."""
    with BurrClient(*live.udp, session=live.session_id, key=live.key_hex,
                    timeout_s=2.0) as client:
        yield client


def _as_id(value: object) -> int | None:
    try:
        return int(float(str(value)))
    except (TypeError, ValueError, OverflowError):
        return None


def _auth(live) -> dict[str, str]:
    return {"Authorization": f"Bearer {live.token}"}


def _send(case, live, checks, loop_probe=None):
    """Send ``case`` (most session ids pointed at the fixture session), run ``checks`` on the
    answer, drop a session it created; with ``loop_probe``, follow an accepted change of the
    fixture session with a datagram, which must be answered without an error."""
    op = (case.method.upper(), case.operation.path)
    sid = (case.path_parameters or {}).get("session_id")
    if op == ("DELETE", "/v1/sessions/{session_id}"):
        # Deleting the fixture session would leave every later example a 404: other ids only
        # (also "1" or "1.0", which the server reads as 1).
        if _as_id(sid) == live.session_id:
            reject()
    elif isinstance(sid, int) and sid % FIXTURE_SHARE:
        case.path_parameters["session_id"] = sid = live.session_id
    response = case.call(base_url=live.url, headers=_auth(live), timeout=120)
    try:
        case.validate_response(response, checks=checks, headers=_auth(live))
    finally:
        if op == ("POST", "/v1/sessions") and response.status_code in (201, 202):
            # Every created session holds a bone in the hot loop: drop it again.
            httpx.delete(f"{live.url}/v1/sessions/{response.json()['id']}",
                         headers=_auth(live), timeout=30.0)
    if loop_probe is not None and op[0] in CHANGES and sid == live.session_id \
            and op[1].startswith("/v1/sessions/{session_id}") and response.status_code < 300:
        try:
            loop_probe.exchange((5.0, -4.0, 30.0), rpm=60_000)
        except ServerError as exc:
            # Healthy again for the next example (and for hypothesis's shrinking, which
            # replays this one): the session as it started.
            live.recreate_session()
            body = json.dumps(case.body) if case.body is not None else ""
            pytest.fail(f"{op[0]} {case.formatted_path} {case.query or ''} {body} was "
                        f"accepted ({response.status_code}), and the next datagram of the "
                        f"session got {ERROR_NAMES.get(exc.code, exc.code)} (for INTERNAL "
                        "the hot loop's log has the traceback)")


@schema.parametrize()
@settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None,
          suppress_health_check=list(HealthCheck))
def test_no_server_errors(case, live, loop_probe):
    """No 5xx, and nothing the API accepts breaks the hot loop."""
    _send(case, live, [not_a_server_error], loop_probe)


@schema.parametrize()
@settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None,
          suppress_health_check=list(HealthCheck))
def test_answers_match_the_schema(case, live):
    """Every answer's body is what the schema documents for its status."""
    _send(case, live, [response_schema_conformance])


def test_the_live_server_publishes_this_schema(live):
    served = httpx.get(f"{live.url}/openapi.json", timeout=30.0).json()
    assert served == PUBLISHED


def _example_path(path: str, live) -> str:
    values = {"session_id": str(live.session_id), "label": "1", "job_id": "0" * 16,
              "name": "any"}
    for key, value in values.items():
        path = path.replace("{" + key + "}", value)
    assert "{" not in path, f"no example value for a parameter of {path}"
    return path


def test_every_route_but_health_needs_the_token(live):
    routes = [(method.upper(), path) for path, item in PUBLISHED["paths"].items()
              for method in item if method in ("get", "put", "post", "patch", "delete")]
    assert len(routes) > 20 and ("GET", "/v1/health") in routes
    with httpx.Client(base_url=live.url, timeout=30.0) as http:
        for method, path in routes:
            url = _example_path(path, live)
            for headers in ({}, {"Authorization": "Bearer " + "x" * 32},
                            {"Authorization": f"Basic {live.token}"},
                            {"Authorization": f"Bearer {live.token}x"}):
                r = http.request(method, url, headers=headers)
                if path == "/v1/health":
                    assert r.status_code == 200, (method, path, r.text)
                    continue
                assert r.status_code == 401, (method, path, headers, r.status_code, r.text)
                assert r.headers.get("www-authenticate") == "Bearer", (method, path)
                assert "token" in r.json()["detail"]
        # The fixture session is still there and the token works.
        r = http.get(f"/v1/sessions/{live.session_id}", headers=_auth(live))
        assert r.status_code == 200
