"""Live telemetry against a real server: the control plane samples the hot loop's own state
from shared memory (``server/api/telemetry.py``), over REST and a WebSocket, while a client
streams a groove over UDP; and it follows a hot loop the supervisor restarted."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import shutil
import signal
import tempfile
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from waiting import wait_until as _wait

from burrforce.client.udp import BurrClient, ServerGone
from burrforce.proto import frames
from burrforce.proto.messages import STATUS_CUTTING, Pose
from burrforce.proto.sequence import seq_after
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.models import Parameters
from burrforce.server.api.stack import ServerStack
from burrforce.server.api.telemetry import TelemetryReader, TickRing, newest_tick
from burrforce.server.haptics.config import HapticsConfig
from burrforce.server.haptics.profiles import PROFILES
from burrforce.server.hotloop.dispatch import Dispatcher
from burrforce.server.hotloop.spec import SessionSpec, build_session
from burrforce.server.record import start_recording

TOKEN = "telemetry-test-token-0123456789"
#: Extra sends of a groove's last pose until one is answered.
SETTLE_TRIES = 10


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    with ServerStack(ServeConfig(http_port=0, udp_port=0,
                                 data_dir=tmp_path_factory.mktemp("telemetry")), TOKEN,
                     journal=False) as st:
        source = st.plane.resolve("phantom:workpiece", None, 0.2)
        st.add_session(source, Parameters(), session_id=7)
        yield st


def _groove(stack, x0_mm: float, n: int = 300, replies: dict | None = None,
            poses: dict | None = None) -> object:
    """A groove along +x in the workpiece (si_mm: engine units are mm); the last reply,
    which is the last packet the server answered: the last pose is sent again until its
    reply comes (an exchange that timed out may still have been answered after the client
    gave up on it, so the reply got before it need not be the server's last)."""
    session = stack.plane.get(7)
    last = None
    with BurrClient(*stack.udp_address, session.id, session.key_hex) as client:
        for i in range(n + SETTLE_TRIES):
            p = (x0_mm + 0.005 * min(i, n - 1), 0.0, -0.6)
            try:
                last = client.exchange(p, rpm=60000.0, timeout_s=0.5 if i < n else 2.0).reply
            except (TimeoutError, ServerGone):
                last = None  # not settled: this packet may yet be answered
                continue
            if replies is not None:
                replies[last.seq] = last
                poses[last.seq] = p
            if i >= n - 1:
                break  # the last packet sent was answered
            time.sleep(0.0005)
    return last


def _get(stack, path: str, token: str | None = TOKEN) -> tuple[int, dict]:
    request = urllib.request.Request(stack.url + path)
    if token is not None:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")


def _server_point(p):
    return frames.Transform(frames.frame(frames.DEFAULT_FRAME)).point_in(p)


def test_samples_follow_the_stream(stack):
    reader = stack.plane.telemetry
    replies: dict = {}
    poses: dict = {}
    samples = []
    done = threading.Event()

    def sample() -> None:
        while not done.is_set():
            s = reader.sample(7)
            if s is not None and s.packet:
                samples.append(s)
            time.sleep(1 / 60)

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        last = _groove(stack, 3.0, n=600, replies=replies, poses=poses)
    finally:
        done.set()
        sampler.join()
    assert last is not None and last.status & STATUS_CUTTING
    # Still: the sample is the last reply the client got, exactly.
    s = reader.sample(7)
    assert s.packet and s.reply_current and s.seq == last.seq
    assert s.force_N == list(last.force) and s.resistive_N == list(last.resistive)
    assert s.status == last.status and "cutting" in s.status_names
    assert s.bone_version == last.bone_version > 0
    assert s.vibration_frequency_Hz == last.vibration_frequency_hz == 1000.0
    assert s.hand_force_magnitude_N == pytest.approx(sum(f * f for f in last.force) ** 0.5)
    assert s.centre_mm == pytest.approx(_server_point(poses[last.seq]), abs=1e-9)
    assert s.axis == pytest.approx([0.0, 0.0, 1.0]) and s.rpm == 60000.0
    assert s.t_client_us == last.t_client_us and s.residence_us == (last.t_send_us
                                                                    - last.t_recv_us)
    assert s.tick_us_p50 is not None and s.tick_us_p50 > 0.0
    # While streaming: samples are packets the client got back. A sample may be torn (a
    # reply being written while it was copied): the force of one packet, the seq of the
    # one before. Most are whole.
    assert len(samples) >= 5
    whole = [x for x in samples if x.seq in replies
             and x.force_N == list(replies[x.seq].force)
             and x.status == replies[x.seq].status]
    assert len(whole) >= 0.8 * len(samples)
    # Packets sent: a sample may be of one whose reply the client gave up on.
    assert all(not seq_after(x.seq, last.seq) for x in samples)


def test_rest_route(stack):
    status, body = _get(stack, "/v1/sessions/7/telemetry")
    assert status == 200 and body["session_id"] == 7 and len(body["centre_mm"]) == 3
    assert body["loop"] == "running"
    # The loop's receive time and this process's clock are one clock: the age grows by the
    # time waited (and the packet is from this test module's grooves: under a minute).
    assert body["packet"] and 0.0 <= body["age_s"] < 60.0
    time.sleep(0.2)
    assert _get(stack, "/v1/sessions/7/telemetry")[1]["age_s"] >= body["age_s"] + 0.2
    assert _get(stack, "/v1/sessions/7/telemetry", token="wrong")[0] == 401
    assert _get(stack, "/v1/sessions/7/telemetry", token=None)[0] == 401
    assert _get(stack, "/v1/sessions/99/telemetry")[0] == 404


def _ws_url(stack, session: int, **query) -> str:
    q = "&".join(f"{k}={v}" for k, v in query.items())
    return stack.url.replace("http", "ws", 1) + f"/v1/sessions/{session}/telemetry/ws?{q}"


def test_websocket_pushes_samples_while_streaming(stack):
    from websockets.sync.client import connect

    streaming = threading.Thread(target=_groove, args=(stack, -3.0, 2000))
    streaming.start()
    try:
        with connect(_ws_url(stack, 7, token=TOKEN, hz=30), open_timeout=10) as ws:
            json.loads(ws.recv(timeout=10))  # the first: connected, sampling
            got = []
            end = time.monotonic() + 1.0
            while time.monotonic() < end:
                got.append(json.loads(ws.recv(timeout=5)))
    finally:
        streaming.join()
    assert len(got) >= 15  # 30 asked for; a shared, noisy machine
    assert all(m["session_id"] == 7 for m in got)
    assert len({m["seq"] for m in got}) >= 10  # each a newer packet


def test_a_browser_sends_the_token_as_a_subprotocol(stack):
    """A browser cannot set a WebSocket's headers: it offers ``burrforce, bearer.TOKEN``, and
    the server chooses ``burrforce`` (a browser fails a handshake that chooses none)."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    _groove(stack, 2.0, 20)  # a packet to sample
    with connect(_ws_url(stack, 7, hz=30), subprotocols=["burrforce", f"bearer.{TOKEN}"],
                 open_timeout=10) as ws:
        assert ws.subprotocol == "burrforce"
        assert json.loads(ws.recv(timeout=10))["session_id"] == 7
    with connect(_ws_url(stack, 7, hz=30), subprotocols=["burrforce", "bearer.not-the-token"],
                 open_timeout=10) as ws:
        with pytest.raises(ConnectionClosed) as err:
            ws.recv(timeout=10)
        assert err.value.rcvd.code == 4401


def test_websocket_refuses_a_bad_token_hz_and_session(stack):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    for session, query, code, says in (
            (7, {"token": "wrong"}, 4401, "token"),
            (7, {"token": TOKEN, "hz": 5}, 4422, "hz must be in 10..60"),
            (7, {"token": TOKEN, "hz": 61}, 4422, "hz must be in 10..60"),
            (7, {"token": TOKEN, "hz": "fast"}, 4422, "must be an integer"),
            (99, {"token": TOKEN}, 4404, "no session 99")):
        with connect(_ws_url(stack, session, **query), open_timeout=10) as ws:
            with pytest.raises(ConnectionClosed) as err:
                ws.recv(timeout=10)
        assert err.value.rcvd.code == code and says in err.value.rcvd.reason


def test_websocket_from_a_foreign_origin_is_refused_unless_configured(stack):
    """A browser says which page opened a WebSocket (Origin) and sends a token it holds along:
    a page of another site is refused (4403) even with the right token; the server's own
    pages (the live view), clients that send no Origin (the SDKs) and origins named in
    cors_origins are admitted."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    _groove(stack, 2.0, 20)  # a packet to sample
    url = _ws_url(stack, 7, token=TOKEN, hz=30)
    own = stack.url  # http://127.0.0.1:PORT: what the live view's pages are served from
    host, port = own.removeprefix("http://").rsplit(":", 1)
    for origin in ("https://evil.example", f"http://{host}:{int(port) + 1}",
                   f"http://localhost.evil.example:{port}", "null"):
        with connect(url, origin=origin, open_timeout=10) as ws:
            with pytest.raises(ConnectionClosed) as err:
                ws.recv(timeout=10)
        assert err.value.rcvd.code == 4403, origin
        assert origin in err.value.rcvd.reason and "cors_origins" in err.value.rcvd.reason
    for origin in (own, own.upper().replace("HTTP", "http"), None):
        with connect(url, origin=origin, open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["session_id"] == 7, origin
    app_state = stack.server.config.app.state  # serve's cors_origins, as create_app set it
    configured = app_state.ws_origins
    try:
        app_state.ws_origins = ("https://viewer.example",)
        with connect(url, origin="https://viewer.example", open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["session_id"] == 7
        app_state.ws_origins = ("*",)
        with connect(url, origin="https://evil.example", open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["session_id"] == 7
    finally:
        app_state.ws_origins = configured


def test_the_reader_follows_a_restarted_hot_loop(stack):
    reader = stack.plane.telemetry
    _groove(stack, 5.0, n=20)
    before = reader.sample(7)
    rows_before = len(stack.plane.history.view(7).t_s)
    restarts = len(stack.supervisor.restarts)
    seen: set[str] = set()
    watching = threading.Event()

    def watch() -> None:  # the loop's state as the REST route reports it
        while not watching.is_set():
            seen.add(_get(stack, "/v1/sessions/7/telemetry")[1].get("loop"))

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        os.kill(stack.hot.pid, signal.SIGKILL)
        assert _wait(lambda: len(stack.supervisor.restarts) > restarts
                     and stack.supervisor.state == "running")
    finally:
        watching.set()
        watcher.join()
    # The window may be shorter than a poll: only what was seen is checked.
    assert seen <= {"running", "down", "restarting"}
    after = reader.sample(7)
    assert after.installs > before.installs and not after.packet and after.age_s is None
    last = _groove(stack, 6.0, n=50)
    assert last is not None
    s = reader.sample(7)
    assert s.packet and s.seq == last.seq and s.force_N == list(last.force)
    # The session's history goes on through the restart: the old rows and the new install's.
    assert _wait(lambda: stack.plane.history.view(7).t_s[-1] == s.t_recv_s)
    view = stack.plane.history.view(7)
    assert len(view.t_s) > rows_before and view.installs[-1] == s.installs
    assert view.installs[0] <= before.installs and np.all(np.diff(view.t_s) >= 0.0)


def test_a_bone_reset_while_streaming_switches_slots_and_samples_go_on(stack):
    """A reset builds the new session in the file's other slot while the old one streams,
    then switches: the reader follows (installs + 1), samples continue, and the history
    keeps both."""
    reader = stack.plane.telemetry
    _groove(stack, 2.0, n=20)
    before = reader.sample(7)
    result: dict = {}
    streaming = threading.Thread(
        target=lambda: result.setdefault("last", _groove(stack, -2.0, n=1500)))
    streaming.start()
    try:
        assert _wait(lambda: reader.sample(7).key != before.key)  # streaming
        job = stack.plane.reset(7)
        assert stack.plane.wait(job, 60.0) and job.state == "done", job.error
    finally:
        streaming.join()
    last = result["last"]
    assert last is not None
    s = reader.sample(7)
    assert s.installs == before.installs + 1
    assert s.packet and s.seq == last.seq and s.force_N == list(last.force)
    assert _wait(lambda: stack.plane.history.view(7).t_s[-1] == s.t_recv_s)
    view = stack.plane.history.view(7)
    assert {before.installs, s.installs} <= set(view.installs.tolist())
    assert np.all(np.diff(view.t_s) >= 0.0)
    # The live report spans both, and says the volumes count from the reset.
    status, report = _get(stack, "/v1/sessions/7/report")
    assert status == 200 and report["ticks"] == len(view.t_s)
    assert any("the bone was reloaded" in n for n in report["notes"])


def test_a_telemetry_websocket_over_the_limit_is_closed_with_4503(stack, monkeypatch):
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    from burrforce.server.api import routes_telemetry

    monkeypatch.setattr(routes_telemetry, "MAX_TELEMETRY_SOCKETS", 2)
    url = _ws_url(stack, 7, token=TOKEN, hz=10)
    with connect(url, open_timeout=10) as a, connect(url, open_timeout=10) as b:
        json.loads(a.recv(timeout=10))
        json.loads(b.recv(timeout=10))
        with connect(url, open_timeout=10) as c:
            with pytest.raises(ConnectionClosed) as err:
                c.recv(timeout=10)
        assert err.value.rcvd.code == 4503 and "limit (2)" in err.value.rcvd.reason
    # Both closed: their places are free again (the server sees them go asynchronously).
    def fits() -> bool:
        with connect(url, open_timeout=10) as d:
            try:
                return "session_id" in json.loads(d.recv(timeout=10))
            except ConnectionClosed:
                return False

    assert _wait(fits, timeout_s=10.0)


@given(st.integers(2, 12), st.data())
def test_the_newest_tick_is_found_in_a_ring_written_with_wraparound(size, data):
    """The hot loop writes tick times into a ring in order, wrapping; the reader, which
    does not see the head, finds the newest entry from what changed since its last look,
    whenever it can tell (fewer than a lap of new entries), and is never wrong: None
    otherwise. (An entry equal to the one the reader last saw in its slot is the documented
    blind spot: ns tick times rarely repeat; the writer here never does that.)"""
    ring = TickRing()
    ticks = np.zeros(size, np.int64)
    seen = ticks.copy()  # the ring at the reader's last look
    written = 0
    newest = None
    looked = False
    known = False  # the previous look found the newest
    for k in data.draw(st.lists(st.integers(0, 2 * size), min_size=1, max_size=8)):
        for _ in range(k):
            value = data.draw(st.integers(1, 50))
            while value in (ticks[written % size], seen[written % size]):
                value += 50
            ticks[written % size] = value
            newest = value
            written += 1
        last, _, _ = newest_tick(ring, 1, ticks.copy())
        if written == 0:
            assert last is None
        else:
            assert last is None or last == newest / 1e3
            exact = (written < size or (looked and 0 < k < size)
                     or (looked and k == 0 and known))
            if exact:
                assert last == newest / 1e3
        looked = True
        known = last is not None
        seen = ticks.copy()


def test_replies_built_in_python_are_kept_like_the_raw_replys(tmp_path):
    """Recording and the device-limited output answer in Python, which keeps its reply where
    the raw kernel keeps its own: the sample shows those packets' replies, not the last raw
    one's."""
    directory = Path(tempfile.mkdtemp(dir="/dev/shm")) if Path("/dev/shm").is_dir() \
        else tmp_path
    reader = TelemetryReader(directory)
    if not reader.available:
        pytest.skip("no /dev/shm here (allowed in CI)")
    try:
        session = build_session(SessionSpec(session_id=3, bone="phantom:workpiece",
                                            voxel_mm=0.5, telemetry=reader.path(3),
                                            publish=False))
        dispatcher = Dispatcher()
        dispatcher.add(session)
        dispatcher.warm_up()
        session.publish_telemetry()
        t_us = [1000]

        def send(seq: int, x_mm: float, rpm: float) -> None:
            t_us[0] += 1000
            session.respond(Pose(3, seq, t_us[0], (x_mm, 0.0, 50.0), (0.0, 0.0, 0.0, 1.0),
                                 rpm, True), time.monotonic_ns())

        for seq in range(1, 4):
            send(seq, 0.0, 60_000.0)
        raw = reader.sample(3)
        assert raw.packet and raw.reply_current and raw.seq == 3
        assert raw.vibration_frequency_Hz == pytest.approx(1000.0)
        recording = start_recording(session, str(directory / "r.burrrec"))
        for seq in range(4, 40):
            send(seq, 0.001 * seq, 30_000.0)
        during = reader.sample(3)
        recording.detach()
        recording.close()
        assert during.packet and during.reply_current and during.seq == 39
        assert during.vibration_frequency_Hz == pytest.approx(500.0)
        assert during.rpm == 30_000.0 and during.error == "ok" and during.residence_us >= 0
        session.configure(dataclasses.replace(session.config, haptics=HapticsConfig(
            output="raw", profile=PROFILES["generic"])))
        for seq in range(40, 60):
            send(seq, 0.001 * seq, 20_000.0)
        limited = reader.sample(3)
        assert limited.packet and limited.reply_current and limited.seq == 59
        assert limited.rpm == 20_000.0
        assert limited.vibration_frequency_Hz == pytest.approx(20_000.0 / 60.0)
    finally:
        reader.close()
        shutil.rmtree(directory, ignore_errors=True)


def test_a_reused_session_id_gets_a_file_of_its_own(stack):
    """Deleting a session and creating one with the same id gives the new one a fresh,
    live file (the old one is discarded while the id is still taken)."""
    source = stack.plane.resolve("phantom:workpiece", None, 0.5)
    stack.add_session(source, Parameters(), session_id=41)
    assert stack.plane.telemetry.sample(41) is not None
    stack.plane.delete_session(41)
    assert stack.plane.telemetry.sample(41) is None
    stack.add_session(source, Parameters(), session_id=41)
    try:
        assert stack.plane.telemetry.sample(41) is not None
        assert Path(stack.plane.telemetry.path(41)).exists()
    finally:
        stack.plane.delete_session(41)


def test_installs_alternate_slots_and_the_header_names_both_in_one_word(tmp_path):
    """A replacement session is built in the slot the installed one does not write; the
    header's one word gives the reader the count and the slot together."""
    from burrforce.server.hotloop import telemetry as block

    path = tmp_path / "t.bin"
    block.create(path)
    eye = np.eye(3)
    seen = []
    for _ in range(4):
        slot = block.TelemetrySlot(path)
        slot.activate(np.zeros(3), eye)
        with open(path, "rb") as f:
            state = int(np.frombuffer(f.read(block.PAGE), np.int64)[block.H_STATE])
        seen.append(block.installs_and_slot(state))
    assert seen == [(1, 0), (2, 1), (3, 0), (4, 1)]


def test_the_force_is_also_given_in_the_server_frame(stack):
    """A Unity session (left-handed, y up, metres): the reply's force is in Unity's axes,
    ``force_server_N`` in the server's, where the bone's top face pushes the burr up (+z)."""
    source = stack.plane.resolve("phantom:workpiece", None, 0.2)
    stack.add_session(source, Parameters(frame="unity"), session_id=11)
    try:
        unity = frames.Transform(frames.frame("unity"))
        session = stack.plane.get(11)
        # The feed velocity is sent, not left to the packets' timing: the force is
        # proportional to it, and a loaded machine spaces the packets out.
        feed = unity.vector_out((5.0, 0.0, 0.0))  # mm/s: 0.005 mm a packet at 1 kHz
        with BurrClient(*stack.udp_address, session.id, session.key_hex) as client:
            for i in range(300):
                p = unity.point_out((10.0 + 0.005 * i, 0.0, 1.5))  # 0.5 mm deep
                with contextlib.suppress(TimeoutError, ServerGone):
                    client.exchange(p, rpm=60000.0, velocity=feed, timeout_s=0.5)
        s = stack.plane.telemetry.sample(11)
        assert s.reply_current and s.hand_force_magnitude_N > 0.5
        assert s.force_server_N == pytest.approx(list(unity.direction_in(s.force_N)), abs=1e-9)
        assert s.force_server_N[2] > 0.5 * s.hand_force_magnitude_N  # up, out of the bone
        assert s.force_N[1] > 0.5 * s.hand_force_magnitude_N  # Unity's up is +y
    finally:
        stack.plane.delete_session(11)
