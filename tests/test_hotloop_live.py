"""The hot loop as it runs: its own process, real UDP sockets on 127.0.0.1, the real clients,
``burrforce serve`` and ``burrforce client demo`` as subprocesses. Every loop is bounded."""

from __future__ import annotations

import asyncio
import math
import random
import socket
import time

import msgpack
import pytest

from burrforce.client import AsyncBurrClient, BurrClient, ServerError, line, stream
from burrforce.proto.codec import decode_server_message, encode_pose
from burrforce.proto.messages import (
    BAD_TAG,
    FLAG_NEW_STREAM,
    STATUS_CUTTING,
    UNKNOWN_SESSION,
    Notice,
    Pose,
)
from burrforce.proto.tag import Tagger
from burrforce.server.hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec

KEY = bytes(range(100, 132))
KEYED, OPEN = 1, 2
ON_BONE = (5.0, 0.0, 1.5)  # the workpiece's top face is z = 0: 0.5 mm deep for R = 2


@pytest.fixture(scope="module")
def server():
    config = HotLoopConfig(sessions=(
        SessionSpec(KEYED, "phantom:workpiece", 0.25, KEY),
        SessionSpec(OPEN, "phantom:workpiece", 0.5, None, SessionConfig(frame="unity")),
    ))
    with HotLoopProcess(config) as hot:
        yield hot


def test_exchange_returns_a_verified_reply_with_its_round_trip(server):
    with BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
        first = c.exchange((5.0, 0.0, 30.0), rpm=60_000)
        assert first.reply.error == 0 and first.rtt_us > 0
        # Server and client share the machine's monotonic clock: the offset is ~0.
        assert abs(first.offset_us) < 50_000
        results = [c.exchange((5.0 + 0.003 * k, -4.0, 1.5), rpm=60_000) for k in range(200)]
    assert results[-1].reply.status & STATUS_CUTTING
    assert results[-1].reply.removed_mm3 > 0.0
    assert c.counters["bad_tag"] == 0 and c.counters["timeouts"] == 0


def test_wrong_key_and_unknown_session_are_reported(server):
    with BurrClient(*server.address, session=KEYED, key=b"wrong", timeout_s=2.0) as c:
        with pytest.raises(ServerError) as err:
            c.exchange((5.0, 0.0, 30.0))
        assert err.value.code == BAD_TAG and "key" in str(err.value)
    with BurrClient(*server.address, session=4242, key=KEY, timeout_s=2.0) as c:
        with pytest.raises(ServerError) as err:
            c.exchange((5.0, 0.0, 30.0))
        assert err.value.code == UNKNOWN_SESSION


def test_asyncio_client(server):
    async def run():
        c = await AsyncBurrClient.connect(*server.address, session=KEYED, key=KEY,
                                          timeout_s=2.0)
        try:
            replies = [await c.exchange((8.0 + 0.003 * k, 4.0, 1.5), rpm=60_000)
                       for k in range(100)]
            return replies, dict(c.counters)
        finally:
            c.close()

    replies, counters = asyncio.run(run())
    assert replies[-1].reply.status & STATUS_CUTTING
    assert counters["bad_tag"] == 0 and counters["received"] == 100


def test_streaming_a_trajectory_at_1khz(server):
    with BurrClient(*server.address, session=OPEN, key=None) as c:
        # Unity: metres, y up, z forward (server +x). The burr 0.5 mm into the block's top
        # face, from x = 12 to 18 mm, the tool upright (Unity's default tool axis is +y).
        waypoints = list(line((0.0, 0.0015, 0.012), (0.0, 0.0015, 0.018), 0.003,
                              rpm=60_000))
        out = stream(c, waypoints, rate_hz=1000.0)
    assert len(out.results) == len(waypoints) == 2001
    assert out.lost <= 2  # loopback loses nothing unless this machine stalls badly
    cutting = [r for r in out.results[500:] if r is not None]
    assert all(r.reply.status & STATUS_CUTTING for r in cutting)
    # Feed velocity came from the stamped schedule: 3 mm/s along Unity's +z, in metres/s.
    vz = [r.reply.feed_velocity[2] for r in cutting]
    assert sum(vz) / len(vz) == pytest.approx(0.003, rel=1e-6)


def _corpus(rng: random.Random, tagger: Tagger, n: int):
    """Random and mutated datagrams, the attacks of the issue included."""
    valid = encode_pose(Pose(KEYED, 10, 10_000, ON_BONE, (0.0, 0.0, 0.0, 1.0), 60_000.0,
                             True), tagger)
    fixed = [
        b"", b"\xc1", b"\x91" * 500, b"\xdd\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff",
        msgpack.packb([1, 1, KEYED, 1, 1, [math.nan] * 3, [0.0, 0.0, 0.0, 1.0], 1.0, True,
                       None, 0, None]),
        msgpack.packb([2, 1, KEYED, 1, 1]), msgpack.packb([1, 9, KEYED, 1, 1] + [0] * 7),
        msgpack.packb({"version": 1}), msgpack.packb("x" * 400), bytes(600),
        msgpack.packb([1, 1, KEYED, 1, 1, [1e308] * 3, [0.0] * 4, 1.0, True, [1.0] * 3, 0,
                       b"\0" * 16]),
    ]
    for i in range(n):
        kind = i % 5
        if kind == 0:
            yield rng.randbytes(rng.randint(0, 600))
        elif kind == 1:
            k = rng.randrange(len(valid))
            yield valid[:k] + bytes([rng.randrange(256)]) + valid[k + 1:]
        elif kind == 2:
            yield valid[:rng.randrange(len(valid))]
        elif kind == 3:
            yield fixed[i % len(fixed)]
        else:  # well-formed but foreign: another key, another session, replays of old seqs
            pose = Pose(rng.choice((KEYED, OPEN, 7)), rng.randrange(1 << 32),
                        rng.randrange(1 << 40),
                        (rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-50, 50)),
                        (0.0, 0.0, 0.0, 1.0), rng.uniform(-1e5, 1e5), rng.random() < 0.5)
            yield encode_pose(pose, Tagger(b"attacker"))


def test_fuzz_100k_datagrams_against_the_live_server(server):
    """At least 100 000 random and mutated datagrams; the server counts every one, answers
    none of them with force, and still answers a real client correctly afterwards."""
    n = 100_000
    before = server.stats()["counters"]
    rng = random.Random(20261122)
    tagger = Tagger(KEY)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(server.address)
    sock.setblocking(False)
    sent = 0
    batch = 200
    pending: list[bytes] = []
    for data in _corpus(rng, tagger, n):
        pending.append(data)
        if len(pending) == batch:
            for d in pending:
                sock.send(d)
            sent += len(pending)
            pending.clear()
            # Let the server keep up, so the kernel's receive buffer never drops any: the
            # test is about the server's handling of each datagram, not about the kernel.
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                received = server.stats()["counters"]["received"] - before["received"]
                if received >= sent - batch:
                    break
                time.sleep(0.002)
            while True:  # drain the notices the server sent back
                try:
                    sock.recv(2048)
                except BlockingIOError:
                    break
    sock.close()
    deadline = time.monotonic() + 20.0
    while time.monotonic() < deadline:
        after = server.stats()["counters"]
        if after["received"] - before["received"] >= sent:
            break
        time.sleep(0.05)
    delta = {k: after[k] - before[k] for k in after}
    assert sent == n
    assert delta["received"] == n
    rejected = sum(v for k, v in delta.items()
                   if k not in ("received", "replied", "noticed", "notices_suppressed",
                                "send_errors"))
    # Every datagram was answered with a reply, or rejected under exactly one reason.
    assert delta["replied"] + rejected - delta["bad_value"] == n
    assert delta["internal"] == 0
    assert delta["malformed"] > 10_000 and delta["bad_tag"] > 10_000
    # The server is alive and right: a real client still cuts.
    assert server.is_alive()
    with BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
        c.exchange((20.0, 4.0, 1.5), rpm=60_000, flags=FLAG_NEW_STREAM)
        r = [c.exchange((20.0 + 0.003 * k, 4.0, 1.5), rpm=60_000) for k in range(1, 50)]
    assert r[-1].reply.error == 0 and r[-1].reply.status & STATUS_CUTTING


def test_sessions_are_added_restarted_and_removed_while_the_loop_runs(server):
    """The commands the control plane will use: a new session answers at once (warmed, its
    bone's voxel size reported), a stream restart forgets the sequence, removal ends it."""
    info = server.call("add_session", spec=SessionSpec(9, "phantom:workpiece", 0.5, KEY))
    assert info == {"voxel_mm": 0.5}
    with pytest.raises(RuntimeError, match="session 9 exists"):
        server.call("add_session", spec=SessionSpec(9, "phantom:workpiece", 0.5, KEY))
    tagger = Tagger(KEY)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(server.address)
    sock.settimeout(2.0)

    def pose(seq: int) -> bytes:
        return encode_pose(Pose(9, seq, time.monotonic_ns() // 1000, (5.0, 0.0, 30.0),
                                (0.0, 0.0, 0.0, 1.0), 0.0, False), tagger)

    try:
        sock.send(pose(100))
        assert decode_server_message(sock.recv(2048)).seq == 100
        sock.send(pose(5))  # stale: never answered
        with pytest.raises(TimeoutError):
            sock.settimeout(0.2)
            sock.recv(2048)
        server.call("restart_stream", session_id=9)
        sock.settimeout(2.0)
        sock.send(pose(5))  # a new stream accepts any sequence number
        assert decode_server_message(sock.recv(2048)).seq == 5
        assert server.stats()["sessions"][9]["stale"] == 1
        assert server.call("remove_session", session_id=9) is True
        assert server.call("remove_session", session_id=9) is False
        sock.send(pose(6))
        notice = decode_server_message(sock.recv(2048))
        assert isinstance(notice, Notice) and notice.error == UNKNOWN_SESSION
    finally:
        sock.close()


def test_stop_closes_the_port():
    hot = HotLoopProcess(HotLoopConfig(sessions=(SessionSpec(1, "phantom:workpiece", 0.5),)))
    host, port = hot.start()
    assert hot.is_alive()
    hot.stop()
    assert not hot.is_alive()
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind((host, port))  # free again
    probe.close()


def test_a_bad_bone_fails_the_start_with_its_reason(tmp_path):
    hot = HotLoopProcess(HotLoopConfig(sessions=(SessionSpec(1, str(tmp_path / "no.nrrd")),)))
    with pytest.raises(RuntimeError, match=r"no\.nrrd"):
        hot.start()
    assert not hot.is_alive()
