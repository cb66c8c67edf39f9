"""A pool of hot loops (``serve --workers N``) against real servers: sessions are placed on the
least-loaded worker, each answers on its worker's UDP port, a killed worker comes back on its
port with its sessions' carving while the other workers' sessions never miss a reply, and bad
pool settings fail clearly before anything starts."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest
from waiting import wait_until as _wait

from burrforce.client.udp import BurrClient, ServerError, ServerGone
from burrforce.proto.messages import UNKNOWN_SESSION
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.models import Parameters
from burrforce.server.api.stack import ServerStack
from burrforce.server.hotloop.pool import spawn_pool, start_pool

TOKEN = "workers-test-token-0123456789"


def _pool(tmp_path, workers: int = 2) -> ServerStack:
    return ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path,
                                   workers=workers), TOKEN, journal=False)


def _cut(client: BurrClient, x0_mm: float, n: int = 150) -> int:
    """A groove in the workpiece along +x; returns the replies that came back."""
    got = 0
    for i in range(n):
        try:
            client.exchange((x0_mm + 0.005 * i, 0.0, -0.6), rpm=60000.0, timeout_s=0.5)
            got += 1
        except (TimeoutError, ServerGone):
            pass
    return got


def test_sessions_are_spread_over_workers_and_answer_on_their_workers_port(tmp_path):
    with _pool(tmp_path) as stack, httpx.Client(
            base_url=stack.url + "/v1", timeout=120.0,
            headers={"Authorization": f"Bearer {TOKEN}"}) as api:
        views = []
        for _ in range(3):
            r = api.post("/sessions", json={"bone": {"source": "phantom:workpiece",
                                                     "voxel_mm": 0.25}})
            assert r.status_code == 201, r.text
            views.append(r.json())
        # No traffic yet, so no measured work: session count decides, ties to the lowest.
        assert [v["worker"] for v in views] == [0, 1, 0]
        ports = [h.address[1] for h in stack.workers]
        assert len(set(ports)) == 2
        for v in views:
            assert v["udp"]["port"] == ports[v["worker"]]
            assert api.get(f"/sessions/{v['id']}").json()["worker"] == v["worker"]
            # hello → NEW_STREAM → POSE → REPLY on the session's own worker.
            with BurrClient(v["udp"]["host"], v["udp"]["port"], v["id"], v["key"],
                            timeout_s=5.0) as c:
                result = c.exchange((20.0, 0.0, 5.0))
            assert result.reply is not None
        for w, hot in enumerate(stack.workers):
            live = hot.call("stats")["sessions"]
            assert sorted(live) == sorted(v["id"] for v in views if v["worker"] == w)
            assert all(s["accepted"] >= 1 for s in live.values())
        # A session's datagrams to another worker's port find no session there.
        wrong = next(v for v in views if v["worker"] == 1)
        with BurrClient(wrong["udp"]["host"], ports[0], wrong["id"], wrong["key"],
                        timeout_s=0.5) as c:
            with pytest.raises(ServerError) as err:
                c.exchange((20.0, 0.0, 5.0), timeout_s=5.0)
        assert err.value.code == UNKNOWN_SESSION

        health = httpx.get(stack.url + "/v1/health", timeout=10).json()
        assert health["hot_loop"] is True and health["udp"]["port"] == ports[0]
        assert [w["index"] for w in health["workers"]] == [0, 1]
        assert [w["udp"]["port"] for w in health["workers"]] == ports
        assert [w["pid"] for w in health["workers"]] == [h.pid for h in stack.workers]
        assert [w["sessions"] for w in health["workers"]] == [2, 1]
        assert {w["state"] for w in health["workers"]} == {"running"}
        assert [w["restarts"] for w in health["workers"]] == [0, 0]
        assert [w["realtime"] for w in health["workers"]] == [False, False]  # not asked for

        plane = stack.plane
        # Measured load wins over the count: worker 1's one session is busy, worker 0's
        # two are idle, so the next goes to worker 0.
        busy = wrong["id"]
        plane.work_us_per_s = lambda: {busy: 400_000.0}
        assert plane.place() == 0
        plane.work_us_per_s = lambda: {views[0]["id"]: 400_000.0}
        assert plane.place() == 1

        assert _wait(lambda: stack.stats.latest and len(stack.stats.latest["sessions"]) == 3)
        text = api.get(stack.url + "/metrics").text
        assert 'burrforce_worker_up{worker="1"} 1.0' in text
        assert 'burrforce_worker_sessions{worker="0"} 2.0' in text
        assert 'burrforce_packets_total{outcome="received"}' in text


def test_a_killed_worker_comes_back_alone_with_its_sessions_carving(tmp_path):
    with _pool(tmp_path) as stack:
        source = stack.plane.resolve("phantom:workpiece", None, 0.2)
        steady = stack.add_session(source, Parameters(), session_id=5)
        victim = stack.add_session(source, Parameters(), session_id=6)
        assert (steady.worker, victim.worker) == (0, 1)
        steady_address = stack.plane.address(steady)
        victim_address = stack.plane.address(victim)
        pid0, pid1 = (h.pid for h in stack.workers)

        with BurrClient(*victim_address, victim.id, victim.key_hex) as client:
            assert _cut(client, 3.0) > 0
        swept_before = victim.reader.swept.copy()
        version_before = victim.reader.version
        assert version_before > 0

        sent = [0]
        replied = [0]
        stop = threading.Event()

        def stream() -> None:
            with BurrClient(*steady_address, steady.id, steady.key_hex) as c:
                while not stop.is_set():
                    sent[0] += 1
                    try:
                        # Generous: a reply late on a busy machine is not a missed one.
                        c.exchange((20.0, 0.0, 5.0), timeout_s=5.0)
                        replied[0] += 1
                    except (TimeoutError, ServerGone):
                        pass
                    time.sleep(0.001)

        streamer = threading.Thread(target=stream, daemon=True)
        streamer.start()
        assert _wait(lambda: replied[0] > 20)
        received_before = stack.stats.poll()["counters"]["received"]
        os.kill(pid1, signal.SIGKILL)
        assert _wait(lambda: stack.supervisor.restarts and stack.supervisor.state == "running")
        before = replied[0]
        assert _wait(lambda: replied[0] > before + 20)  # streamed on after the restart too
        stop.set()
        streamer.join(30.0)
        assert not streamer.is_alive()
        assert sent[0] == replied[0]
        # The pool's counters go on from where they were: the new worker's start from zero,
        # the dead one's are kept (a drop would read as a reset of every worker's).
        assert stack.stats.poll()["counters"]["received"] > received_before + 20

        restart = stack.supervisor.restarts[-1]
        assert restart.worker == 1 and restart.sessions == 1 and "SIGKILL" in restart.reason
        assert stack.workers[0].pid == pid0 and stack.workers[1].pid != pid1
        assert stack.plane.address(victim) == victim_address
        assert stack.plane.address(steady) == steady_address
        # Worker 0 was never touched: its session's stream never ended.
        stats0 = stack.workers[0].call("stats")["sessions"]
        assert list(stats0) == [steady.id] and stats0[steady.id]["wrong_stream"] == 0
        assert list(stack.workers[1].call("stats")["sessions"]) == [victim.id]

        with BurrClient(*victim_address, victim.id, victim.key_hex) as client:
            for _ in range(400):
                try:
                    result = client.exchange((20.0, 0.0, 5.0), timeout_s=0.25)
                    break
                except (TimeoutError, ServerGone):
                    time.sleep(0.025)
            else:
                raise AssertionError("the restarted worker never answered")
        assert result.reply.bone_version == version_before
        assert np.array_equal(victim.reader.swept, swept_before)

        health = httpx.get(stack.url + "/v1/health", timeout=10).json()
        assert [w["restarts"] for w in health["workers"]] == [0, 1]
        assert health["supervisor"]["last_restart"]["worker"] == 1


def _serve(tmp_path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, HOME=str(tmp_path), XDG_CACHE_HOME=str(tmp_path / "cache"))
    return subprocess.run(
        [sys.executable, "-m", "burrforce.server.cli", "serve", "--http-port", "0",
         "--data-dir", str(tmp_path / "data"), "--connection-file",
         str(tmp_path / "conn.json"), "--no-auth", *args],
        capture_output=True, text=True, timeout=300, env=env, stdin=subprocess.DEVNULL)


def test_zero_workers_is_refused(tmp_path):
    done = _serve(tmp_path, "--workers", "0")
    assert done.returncode == 2
    assert "--workers" in done.stderr and "at least 1" in done.stderr


def _port_with_busy_successor() -> tuple[int, socket.socket]:
    """A UDP port P that is free while P + 1 is held by the returned socket."""
    for _ in range(100):
        held = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        held.bind(("127.0.0.1", 0))
        port = held.getsockname()[1] - 1
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                probe.bind(("127.0.0.1", port))
            return port, held
        except OSError:
            held.close()
    raise AssertionError("no free port below a busy one")


def test_a_busy_port_in_the_workers_range_is_refused_before_anything_starts(tmp_path):
    port, held = _port_with_busy_successor()
    with held:
        done = _serve(tmp_path, "--workers", "2", "--udp-port", str(port))
        assert done.returncode == 2
        assert f"UDP port {port + 1} (worker 1 of 2" in done.stderr
        with pytest.raises(RuntimeError, match=f"UDP port {port + 1}"):
            ServerStack(ServeConfig(http_port=0, udp_port=port, data_dir=tmp_path / "d",
                                    workers=2), TOKEN, journal=False).start_backend()


def test_a_pool_spawned_ahead_starts_those_processes_and_refuses_a_wrong_count():
    """``serve`` spawns its hot loops before importing its web stack (their interpreters
    start side by side with it) and starts those very processes later."""
    spawned = spawn_pool("127.0.0.1", 0, 1)
    pids = [hot.pid for hot in spawned]
    with pytest.raises(ValueError, match="1 spawned hot loops for 2 workers"):
        start_pool("127.0.0.1", 0, 2, spawned=spawned)
    pool = start_pool("127.0.0.1", 0, 1, spawned=spawned)
    try:
        assert pool is spawned and [hot.pid for hot in pool] == pids
        assert pool[0].call("stats")["counters"]["received"] == 0
    finally:
        for hot in pool:
            hot.stop()


def test_a_pool_spawned_warm_opens_its_port_before_it_is_started():
    """With every kernel in the cache, ``serve`` sends the config as it spawns: the loop
    loads its kernels and binds its port while the parent still imports; starting it then
    only collects its "ready"."""
    from support.podman import free_port

    port = free_port()
    spawned = spawn_pool("127.0.0.1", port, 1, warm=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                try:
                    probe.bind(("127.0.0.1", port))
                except OSError:
                    break  # the loop holds it: it started without start_pool
            assert time.monotonic() < deadline, "the warm loop never opened its port"
            time.sleep(0.05)
        pool = start_pool("127.0.0.1", port, 1, spawned=spawned)
        assert pool[0].address == ("127.0.0.1", port)
        assert pool[0].call("stats")["counters"]["received"] == 0
    finally:
        for hot in spawned:
            hot.stop()


@pytest.mark.parametrize("text,cap", [("max 100000\n", None), ("200000 100000\n", 2),
                                      ("50000 100000\n", 1), ("150000 100000\n", 2),
                                      ("garbage\n", None)])
def test_usable_cores_follow_a_cgroup_cpu_quota(tmp_path, text, cap):
    from burrforce.server.hotloop.pool import usable_cores

    cpus = len(os.sched_getaffinity(0))
    path = tmp_path / "cpu.max"
    path.write_text(text)
    assert usable_cores(str(path)) == (cpus if cap is None else min(cpus, cap))
    assert usable_cores(str(tmp_path / "missing")) == cpus


def test_a_resumed_session_comes_back_on_the_worker_its_engine_streams_to(tmp_path):
    """Worker 0 holds both sessions once the one placed on worker 1 is gone; placing them
    afresh at the next start would move one to worker 1, a port its engine never heard of."""
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path, workers=2)
    with ServerStack(config, TOKEN) as stack:
        sessions = []
        for sid in (1, 2, 3):
            source = stack.plane.resolve("phantom:workpiece", None, 0.5)
            sessions.append(stack.add_session(source, Parameters(), session_id=sid))
        assert [s.worker for s in sessions] == [0, 1, 0]
        stack.plane.delete_session(2)
        stack.journal.write()
    with ServerStack(config, TOKEN) as stack:
        assert sorted(stack.resumed) == [1, 3]
        assert [stack.plane.sessions[sid].worker for sid in (1, 3)] == [0, 0]
        assert stack.plane.place() == 1  # a new one would have gone to worker 1


def test_new_sessions_are_not_placed_on_a_worker_that_is_down(tmp_path):
    with _pool(tmp_path) as stack:
        stack.supervisor.stop()  # hold the restart: the window a new session must avoid
        hot = stack.workers[1]
        os.kill(hot.pid, signal.SIGKILL)
        assert _wait(lambda: not hot.is_alive())
        assert stack.plane.place() == 0
        assert stack.plane.place() == 0  # however many sessions worker 0 has
