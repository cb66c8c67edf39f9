"""``serve --realtime``: each hot loop's packet thread under SCHED_FIFO, against real servers.

Where it is permitted (root, CAP_SYS_NICE, an RLIMIT_RTPRIO of 5), the loop threads run under
SCHED_FIFO and nothing else in their processes does, a restarted worker is scheduled alike,
and ``/v1/health`` says so per worker. Where it is not, serve says so and serves as without.
"""

from __future__ import annotations

import os
import shutil
import signal
import time

import httpx
import pytest
from scheduling import FIFO_REASON, fifo_permitted
from waiting import wait_until as _wait

from burrforce.client.udp import BurrClient, ServerGone
from burrforce.server.api.config import ServeConfig
from burrforce.server.api.models import Parameters
from burrforce.server.api.stack import ServerStack
from burrforce.server.bench.serve_process import spawn_serve
from burrforce.server.realtime import HOT_LOOP_PRIORITY, is_realtime

TOKEN = "realtime-test-token-0123456789"


def _threads(pid: int) -> list[int]:
    return [int(t) for t in os.listdir(f"/proc/{pid}/task")]


def _answers(address, session) -> bool:
    with BurrClient(*address, session.id, session.key_hex) as client:
        for _ in range(200):
            try:
                return client.exchange((20.0, 0.0, 5.0), timeout_s=0.25).reply is not None
            except (TimeoutError, ServerGone):
                time.sleep(0.025)
    return False


@pytest.mark.skipif(not fifo_permitted(), reason=FIFO_REASON)
def test_realtime_loops_run_under_sched_fifo_alone_and_come_back_so_after_a_crash(tmp_path):
    config = ServeConfig(http_port=0, udp_port=0, data_dir=tmp_path, workers=2, realtime=True)
    with ServerStack(config, TOKEN, journal=False) as stack:
        source = stack.plane.resolve("phantom:workpiece", None, 0.25)
        sessions = [stack.add_session(source, Parameters(), session_id=i) for i in (3, 4)]
        assert [s.worker for s in sessions] == [0, 1]
        for hot in stack.workers:
            # The loop thread (the process's main thread) and nothing else in the process:
            # the commands build sessions and must not hold a core at that priority.
            assert os.sched_getscheduler(hot.pid) == os.SCHED_FIFO
            assert os.sched_getparam(hot.pid).sched_priority == HOT_LOOP_PRIORITY
            others = [t for t in _threads(hot.pid) if t != hot.pid]
            assert others, "the commands and heartbeat threads"
            assert {os.sched_getscheduler(t) for t in others} == {os.SCHED_OTHER}
        for s in sessions:
            assert _answers(stack.plane.address(s), s)
        health = httpx.get(stack.url + "/v1/health", timeout=10).json()
        assert [w["realtime"] for w in health["workers"]] == [True, True]

        # A worker restarted after a crash (or the spare taking its place) is scheduled alike.
        victim = stack.workers[1].pid
        os.kill(victim, signal.SIGKILL)
        assert _wait(lambda: stack.supervisor.restarts and stack.supervisor.state == "running")
        assert stack.workers[1].pid != victim
        assert is_realtime(stack.workers[1].pid)
        assert _answers(stack.plane.address(sessions[1]), sessions[1])
        health = httpx.get(stack.url + "/v1/health", timeout=10).json()
        assert [w["realtime"] for w in health["workers"]] == [True, True]


def _has_sys_nice() -> bool:
    with open("/proc/self/status") as f:
        eff = next(line for line in f if line.startswith("CapEff:")).split()[1]
    return bool(int(eff, 16) & (1 << 23))  # CAP_SYS_NICE


def _without_rt() -> tuple[str, ...]:
    """A command prefix that takes SCHED_FIFO away from what it starts: RLIMIT_RTPRIO 0
    (``prlimit``) and, where this process holds it, CAP_SYS_NICE (``setpriv``: effective,
    inheritable, ambient and bounding, so an exec as root does not get it back)."""
    prefix = [shutil.which("prlimit"), "--rtprio=0:0"]
    if _has_sys_nice():
        prefix = [shutil.which("setpriv"), "--inh-caps=-sys_nice", "--ambient-caps=-sys_nice",
                  "--bounding-set=-sys_nice", "--", *prefix]
    return (*prefix, "--")


@pytest.mark.skipif(shutil.which("prlimit") is None or shutil.which("setpriv") is None,
                    reason="prlimit and setpriv (util-linux) drop what allows SCHED_FIFO")
def test_where_realtime_is_not_permitted_serve_says_so_and_serves(tmp_path):
    serve = spawn_serve(tmp_path, "--realtime", "--workers", "1", "--no-auth", "--bone",
                        "phantom:workpiece", "--voxel-mm", "0.5", prefix=_without_rt())
    try:
        banner = serve.banner
        assert "--realtime: not permitted for 1 of 1 hot loop(s)" in banner, banner
        assert "RLIMIT_RTPRIO" in banner and "real-time budget" in banner
        c = serve.connection
        health = httpx.get(c.http_url + "/v1/health", timeout=10).json()
        assert [w["realtime"] for w in health["workers"]] == [False]
        assert not is_realtime(health["workers"][0]["pid"])
        with BurrClient(c.host, c.udp_port, c.session, None) as client:
            assert client.exchange((20.0, 0.0, 5.0), timeout_s=5.0).reply is not None
    finally:
        serve.stop()
