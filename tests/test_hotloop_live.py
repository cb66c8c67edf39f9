"""The hot loop as it runs: its own process, real UDP sockets on 127.0.0.1, the real clients,
``burrforce serve`` and ``burrforce client demo`` as subprocesses. Every loop is bounded."""

from __future__ import annotations

import asyncio
import math
import os
import random
import select
import socket
import threading
import time

import msgpack
import pytest

from burrforce.client import (
    AsyncBurrClient,
    BurrClient,
    Result,
    ServerError,
    ServerGone,
    StreamTaken,
    Waypoint,
    line,
    stream,
)
from burrforce.proto.codec import decode_server_message, encode_pose
from burrforce.proto.messages import (
    BAD_TAG,
    ERROR_NAMES,
    NEW_STREAM,
    OK,
    STATUS_CUTTING,
    STATUS_STALE,
    UNKNOWN_SESSION,
    WRONG_STREAM,
    Notice,
    Pose,
    Reply,
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
    assert counters["bad_tag"] == 0 and counters["received"] == 101  # the hello's answer too
    assert counters["hellos"] == 1 and counters["streams"] == 1


def test_streaming_a_trajectory_at_1khz(server):
    with BurrClient(*server.address, session=OPEN, key=None) as c:
        # Unity: metres, y up, z forward (server +x). The burr 0.5 mm into the block's top
        # face, from x = 12 to 18 mm, the tool upright (Unity's default tool axis is +y).
        waypoints = list(line((0.0, 0.0015, 0.012), (0.0, 0.0015, 0.018), 0.003,
                              rpm=60_000))
        out = stream(c, waypoints, rate_hz=1000.0)
    assert len(out.results) == len(waypoints) == 2001
    # Until the hello's NEW_STREAM comes back every waypoint goes out as a hello, answered by
    # a notice, not ticked: one round trip's worth of them (6 once, with this machine's cores
    # held by other work). After it, loopback loses nothing unless this machine stalls badly.
    first = next(i for i, r in enumerate(out.results) if r is not None)
    assert first <= 50
    assert sum(r is None for r in out.results[first:]) <= 2
    cutting = [r for r in out.results[500:] if r is not None]
    assert all(r.reply.status & STATUS_CUTTING for r in cutting)
    # Feed velocity came from the stamped schedule: 3 mm/s along Unity's +z, in metres/s.
    vz = [r.reply.feed_velocity[2] for r in cutting]
    assert sum(vz) / len(vz) == pytest.approx(0.003, rel=1e-6)


def _corpus(rng: random.Random, tagger: Tagger, n: int):
    """Random and mutated datagrams, the attacks of the issue included."""
    valid = encode_pose(Pose(KEYED, 10, 10_000, ON_BONE, (0.0, 0.0, 0.0, 1.0), 60_000.0,
                             True, stream=rng.choice((0, 0x5EED))), tagger)
    fixed = [
        b"", b"\xc1", b"\x91" * 500, b"\xdd\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff",
        msgpack.packb([1, 1, KEYED, 1, 1, [math.nan] * 3, [0.0, 0.0, 0.0, 1.0], 1.0, True,
                       None, 0, None]),
        msgpack.packb([2, 1, KEYED, 1, 1, [math.nan] * 3, [0.0, 0.0, 0.0, 1.0], 1.0, True,
                       None, 0, 0x5EED, None]),
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
                        (0.0, 0.0, 0.0, 1.0), rng.uniform(-1e5, 1e5), rng.random() < 0.5,
                        stream=rng.randrange(1 << 32))
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
    # One reason per datagram not ticked normally (hellos count as new_stream); the socket
    # loop's own counters (peers, deferrals) are not reasons.
    rejected = sum(delta[name] for code, name in ERROR_NAMES.items() if code != OK)
    # Every datagram was answered with a reply, or rejected under exactly one reason.
    assert delta["replied"] + rejected - delta["bad_value"] == n
    assert delta["internal"] == 0
    assert delta["malformed"] > 10_000 and delta["bad_tag"] > 10_000
    # The server is alive and right: a real client still cuts.
    assert server.is_alive()
    with BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
        c.exchange((20.0, 4.0, 1.5), rpm=60_000)
        r = [c.exchange((20.0 + 0.003 * k, 4.0, 1.5), rpm=60_000) for k in range(1, 50)]
    assert r[-1].reply.error == 0 and r[-1].reply.status & STATUS_CUTTING


def test_sessions_are_added_restarted_and_removed_while_the_loop_runs(server):
    """The commands the control plane will use: a new session answers at once (warmed, its
    bone's voxel size reported), a stream restart ends the stream (the client says hello and
    gets another), removal ends the session."""
    info = server.call("add_session", spec=SessionSpec(9, "phantom:workpiece", 0.5, KEY))
    assert info == {"voxel_mm": 0.5}
    with pytest.raises(RuntimeError, match="session 9 exists"):
        server.call("add_session", spec=SessionSpec(9, "phantom:workpiece", 0.5, KEY))
    tagger = Tagger(KEY)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(server.address)
    sock.settimeout(2.0)

    def pose(seq: int, stream: int) -> bytes:
        return encode_pose(Pose(9, seq, time.monotonic_ns() // 1000, (5.0, 0.0, 30.0),
                                (0.0, 0.0, 0.0, 1.0), 0.0, False, stream=stream), tagger)

    def hello(seq: int) -> int:
        sock.send(pose(seq, 0))
        data = sock.recv(2048)
        notice = decode_server_message(data)
        assert (notice.error, notice.seq) == (NEW_STREAM, seq) and tagger.verify(data)
        return notice.stream

    try:
        first = hello(99)
        assert server.stats()["sessions"][9]["next_stream"] == ((first + 1) % (1 << 32) or 1)
        sock.send(pose(100, first))
        assert isinstance(decode_server_message(sock.recv(2048)), Reply)
        sock.send(pose(5, first))  # stale: never answered
        with pytest.raises(TimeoutError):
            sock.settimeout(0.2)
            sock.recv(2048)
        server.call("restart_stream", session_id=9)
        sock.settimeout(2.0)
        sock.send(pose(101, first))  # the stream is over
        notice = decode_server_message(sock.recv(2048))
        assert (notice.error, notice.stream) == (WRONG_STREAM, first)
        second = hello(102)
        assert second != first
        sock.send(pose(5, second))  # a new stream accepts any sequence number
        assert decode_server_message(sock.recv(2048)).seq == 5
        stats = server.stats()["sessions"][9]
        assert stats["stale"] == 1 and stats["stream"] == second
        assert (stats["hellos"], stats["streams"], stats["wrong_stream"]) == (2, 2, 1)
        assert server.call("remove_session", session_id=9) is True
        assert server.call("remove_session", session_id=9) is False
        sock.send(pose(6, second))
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


# -- v2 streams: the replay attacks on a real loop --------------------------------------
class Tap:
    """A UDP relay on 127.0.0.1 between one client and the hot loop that keeps a copy of
    every datagram the client sends: what an attacker on the path captures."""

    def __init__(self, server_address: tuple[str, int]) -> None:
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(server_address)
        self.address = self.front.getsockname()
        self.captured: list[bytes] = []
        self._client: tuple[str, int] | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._relay, daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        while not self._stop:
            ready, _, _ = select.select((self.front, self.back), (), (), 0.05)
            for sock in ready:
                try:
                    data, source = sock.recvfrom(4096)
                except OSError:
                    continue
                if sock is self.front:
                    self._client = source
                    self.captured.append(data)
                    self.back.send(data)
                elif self._client is not None:
                    self.front.sendto(data, self._client)

    def close(self) -> None:
        self._stop = True
        self._thread.join(5.0)
        self.front.close()
        self.back.close()


def _capture_keyed_stream(address: tuple[str, int], session: int, n: int) -> list[bytes]:
    """The datagrams of a real client's keyed stream (hello, commit, n − 1 more POSEs
    cutting), captured on their way to the loop."""
    tap = Tap(address)
    try:
        with BurrClient(*tap.address, session=session, key=KEY, timeout_s=2.0) as c:
            for k in range(n):
                assert c.exchange((14.0 + 0.003 * k, -2.0, 1.5), rpm=60_000).reply.error == 0
            assert c.counters["hellos"] == 1 and c.counters["streams"] == 1
    finally:
        tap.close()
    assert len(tap.captured) == n + 1  # the hello, then the n POSEs of the stream
    return tap.captured


def _replay(hot: HotLoopProcess, datagrams: list[bytes]) -> list[object]:
    """Send ``datagrams`` from a fresh socket, wait until the loop has counted every one;
    every answer that came back (decoded)."""
    before = hot.stats()["counters"]["received"]
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.connect(hot.address)
    answers = []
    try:
        for data in datagrams:
            sock.send(data)
        for _ in range(1000):  # bounded: the loop takes microseconds per datagram
            if hot.stats()["counters"]["received"] - before >= len(datagrams):
                break
            time.sleep(0.01)
        sock.settimeout(0.2)  # answers are sent before the next datagram is read
        while True:
            try:
                answers.append(decode_server_message(sock.recv(2048)))
            except TimeoutError:
                return answers
    finally:
        sock.close()


def _assert_not_ticked(answers: list[object], stats_before: dict, stats_after: dict) -> None:
    assert not any(isinstance(a, Reply) for a in answers), answers
    assert stats_after["bone_version"] == stats_before["bone_version"]
    assert stats_after["accepted"] == stats_before["accepted"]


def test_replays_after_idle_and_after_restart_stream_are_never_answered(server):
    """The issue's fault, replayed on a real loop: a captured keyed stream sent again after
    more than a second of idle (v1 restarted the stream and cut with it), then again after a
    REST restart-stream: never a REPLY, never a tick. (Sent from another address than the
    stream's, the open stream's POSEs are refused WRONG_STREAM; from its own, they would be
    stale: ``test_hotloop_dispatch``.)"""
    captured = _capture_keyed_stream(server.address, KEYED, 40)
    time.sleep(1.2)  # past v1's idle restart
    before = server.stats()["sessions"][KEYED]
    answers = _replay(server, captured)
    after = server.stats()["sessions"][KEYED]
    _assert_not_ticked(answers, before, after)
    assert after["wrong_stream"] - before["wrong_stream"] == 40
    # The hello: a notice (an offer of its own), nothing ticked; the POSEs: WRONG_STREAM, as
    # many as the session's bucket answers.
    assert [a.error for a in answers[:1]] == [NEW_STREAM]
    assert {a.error for a in answers[1:]} == {WRONG_STREAM}
    assert after["stream"] == before["stream"]  # the client's stream is untouched
    server.call("restart_stream", session_id=KEYED)
    answers = _replay(server, captured)
    final = server.stats()["sessions"][KEYED]
    _assert_not_ticked(answers, after, final)
    assert {a.error for a in answers} <= {NEW_STREAM, WRONG_STREAM}
    assert final["wrong_stream"] - after["wrong_stream"] == 40 and final["stream"] == 0


def test_a_flood_of_replayed_hellos_never_disturbs_a_live_stream(server):
    captured = _capture_keyed_stream(server.address, KEYED, 3)
    hello = captured[0]
    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    flood.connect(server.address)
    try:
        with BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
            # The client's own velocity: no stamps to go stale on a busy machine.
            first = c.exchange((22.0, -4.0, 1.5), rpm=60_000, velocity=(3.0, 0.0, 0.0))
            stream_no = c.rules.stream
            replies = [first]
            for k in range(1, 60):
                for _ in range(20):
                    flood.send(hello)
                replies.append(c.exchange((22.0 + 0.003 * k, -4.0, 1.5), rpm=60_000,
                                          velocity=(3.0, 0.0, 0.0)))
            assert c.rules.stream == stream_no and c.counters["streams"] == 1
            assert c.counters["wrong_stream"] == 0 and c.counters["timeouts"] == 0
    finally:
        flood.close()
    assert all(r.reply.error == 0 for r in replies)
    assert not any(r.reply.status & STATUS_STALE for r in replies)
    assert replies[-1].reply.status & STATUS_CUTTING


def test_a_client_giving_way_stops_when_another_takes_the_stream(server):
    """A session has one stream: a second client's hello takes it, and the first one's next
    POSE is answered WRONG_STREAM. A client that gives way (``give_way``; `client demo
    --give-way`, as `serve --demo`'s own grooves run) then stops with StreamTaken instead of
    saying hello and taking the stream back, and the other streams on undisturbed. One that
    does not give way takes it back, and the other loses its stream in turn."""
    above = (5.0, 0.0, 30.0)  # far above the bone: nothing is cut
    # The session's handshake notices come from a bucket (100/s, a burst of 20) that a test
    # before may have emptied with replayed hellos: a fifth of a second fills it.
    time.sleep(0.5)
    with (BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0,
                     give_way=True) as polite,
          BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as person):
        assert polite.exchange(above).reply.error == OK
        assert person.exchange(above).reply.error == OK  # its hello took the stream
        with pytest.raises(StreamTaken, match=f"session {KEYED}'s stream"):
            polite.exchange(above)
        assert polite.counters["wrong_stream"] == 1 and polite.counters["hellos"] == 1
        replies = [person.exchange(above) for _ in range(50)]
        assert all(r.reply.error == OK for r in replies)
        assert person.counters["wrong_stream"] == 0 and person.counters["streams"] == 1
        with BurrClient(*server.address, session=KEYED, key=KEY, timeout_s=2.0) as rude:
            assert rude.exchange(above).reply.error == OK
            assert person.exchange(above).reply.error == OK  # after taking it back
            assert person.counters["wrong_stream"] == 1 and person.counters["streams"] == 2


def test_two_clients_saying_hello_at_once_get_streams_of_their_own_and_are_never_silent(
        server):
    """The issue's collision (SPEC 5.2), on a real loop over UDP: two clients say hello
    before either has used its number (v2.0 gave both the same one, and the client with the
    lower sequence numbers then heard nothing at all while the other streamed). Each is
    offered a number of its own; then both stream at 1 kHz for 2 s, taking the session's one
    stream from each other: they never hold the same number, and neither goes unanswered
    while the other is answered (WRONG_STREAM, NEW_STREAM or a REPLY; the handshake's
    notices are rate-limited, 100/s per session, so the other may be answered for a few
    ticks meanwhile; v2.0 let the whole run pass). Silence is counted in ticks in which only
    the other was answered, not in seconds: a stall of this busy machine silences both
    alike, and a backlog read after it counts once."""
    time.sleep(0.5)  # the session's handshake buckets, which tests before may have emptied
    up = (5.0, 0.0, 30.0)  # far above the bone: nothing is cut
    with (BurrClient(*server.address, session=KEYED, key=KEY, first_seq=100_000) as a,
          BurrClient(*server.address, session=KEYED, key=KEY, first_seq=1) as b):
        clients = (a, b)
        for c in clients:  # both hellos out before either answer is read
            c.send(up)
        offers = [c.receive(2.0) for c in clients]
        assert all(isinstance(n, Notice) and n.error == NEW_STREAM for n in offers), offers
        assert offers[0].stream != offers[1].stream
        assert (a.rules.stream, b.rules.stream) == (offers[0].stream, offers[1].stream)
        adopted = [{a.rules.stream}, {b.rules.stream}]
        answered = [0, 0]
        replies = [0, 0]
        # Per client: ticks in a row in which only the other was answered, and the most.
        unheard = [0, 0]
        most_unheard = [0, 0]
        t0 = time.monotonic()
        for k in range(2000):
            time.sleep(max(0.0, t0 + k * 1e-3 - time.monotonic()))
            for c in clients:
                c.send(up)
            heard = [0, 0]
            for i, c in enumerate(clients):
                while (m := c.receive(0.0)) is not None:
                    heard[i] += 1
                    replies[i] += isinstance(m, Result)
                    if c.rules.stream:
                        adopted[i].add(c.rules.stream)
                assert a.rules.stream != b.rules.stream or a.rules.stream == 0
            for i in (0, 1):
                answered[i] += heard[i]
                unheard[i] = 0 if heard[i] else unheard[i] + (heard[1 - i] > 0)
                most_unheard[i] = max(most_unheard[i], unheard[i])
    print(f"two clients: answered {answered}, replies {replies}, streams "
          f"{[len(s) for s in adopted]}, most ticks in a row only the other was answered "
          f"{most_unheard}")
    assert not adopted[0] & adopted[1], adopted
    assert min(replies) > 0 and max(most_unheard) < 100, (replies, most_unheard)


def _closed_udp_port() -> int:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    return port


def test_server_gone_is_one_clear_error_in_send_receive_and_exchange():
    port = _closed_udp_port()
    with BurrClient("127.0.0.1", port, session=1, timeout_s=2.0) as c:
        c.send((0.0, 0.0, 0.0))  # the datagram leaves; the "port unreachable" comes back
        with pytest.raises(ServerGone) as err:
            c.receive()
        assert isinstance(err.value, ConnectionError) and (err.value.host, err.value.port) == (
            "127.0.0.1", port)
        assert "burrforce serve" in str(err.value) and "/v1/health" in str(err.value)
        c.send((0.0, 0.0, 0.0))
        select.select((c.sock,), (), (), 2.0)  # readable once the ICMP error is pending
        with pytest.raises(ServerGone):
            c.send((0.0, 0.0, 0.0))
        with pytest.raises(ServerGone):
            c.exchange((0.0, 0.0, 0.0))


def test_async_client_reports_server_gone():
    port = _closed_udp_port()

    async def run() -> None:
        c = await AsyncBurrClient.connect("127.0.0.1", port, session=1, timeout_s=2.0)
        try:
            with pytest.raises(ServerGone):
                await c.exchange((0.0, 0.0, 0.0))
            c.send((0.0, 0.0, 0.0))
            with pytest.raises(ServerGone):
                await c.receive()
            assert c.counters["icmp_errors"] == 2
        finally:
            c.close()

    asyncio.run(run())


def _loop_config(port: int, next_stream: int | None = None) -> HotLoopConfig:
    return HotLoopConfig(udp_port=port, sessions=(
        SessionSpec(KEYED, "phantom:workpiece", 0.5, KEY, next_stream=next_stream),))


def test_a_restarted_loop_never_answers_the_old_streams_replays():
    """(c) of the issue: the loop restarted on the same port, its session's streams numbered
    from the old stream + 65536 (what the control plane journals): the captured stream is
    refused (WRONG_STREAM), never ticked; a client just says hello and cuts."""
    with HotLoopProcess(_loop_config(0)) as old:
        captured = _capture_keyed_stream(old.address, KEYED, 20)
        last = old.stats()["sessions"][KEYED]["stream"]
        port = old.address[1]
    base = (last + 65536) % (1 << 32) or 1
    with HotLoopProcess(_loop_config(port, base)) as new:
        before = new.stats()["sessions"][KEYED]
        assert before["next_stream"] == base
        answers = _replay(new, captured)
        after = new.stats()["sessions"][KEYED]
        _assert_not_ticked(answers, before, after)
        assert after["wrong_stream"] == 20 and after["stream"] == 0
        with BurrClient(*new.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
            r = [c.exchange((10.0 + 0.003 * k, 2.0, 1.5), rpm=60_000) for k in range(30)]
            # The replayed hello's address holds the first number: the client gets its own.
            assert c.rules.stream == base + 1
        assert r[0].reply.status & STATUS_STALE and r[-1].reply.status & STATUS_CUTTING


def test_a_loop_offers_the_next_stream_its_spec_gives():
    with HotLoopProcess(_loop_config(0, 0xFFFF_FFFF)) as hot:
        assert hot.stats()["sessions"][KEYED]["next_stream"] == 0xFFFF_FFFF
        with BurrClient(*hot.address, session=KEYED, key=KEY, timeout_s=2.0) as c:
            c.exchange((5.0, 0.0, 30.0))
            assert c.rules.stream == 0xFFFF_FFFF
        assert hot.stats()["sessions"][KEYED]["next_stream"] == 1  # wraps, skipping 0


def test_stream_survives_the_server_stopping_and_starting_mid_trajectory():
    """stream() keeps its schedule through an outage: it counts the outage, says so once
    each way, and when the loop is back (on the same port) the client says hello again: the
    first reply is STALE, then cutting resumes."""
    hot = HotLoopProcess(_loop_config(0))
    host, port = hot.start()
    events: list[tuple[bool, int]] = []
    replies_after: list[Reply] = []
    first_results = threading.Event()
    state = {"hot": hot, "results": 0}

    def on_result(i: int, result) -> None:
        state["results"] += 1
        if state["results"] == 300:
            first_results.set()
        # After the client said the loop is back: stream() reports that on the first message
        # from the new loop, before its result (the restarting thread may not have run again
        # yet: on a loaded machine the first replies came before it could flag the restart).
        if events and not events[-1][0]:
            replies_after.append(result.reply)

    def restart() -> None:
        first_results.wait(60.0)
        state["hot"].stop()
        state["hot"] = HotLoopProcess(_loop_config(port))
        state["hot"].start()

    def waypoints():
        """Round a 4 mm circle on the top face at 3 mm/s, 0.5 mm deep (never back into its
        own groove within a lap: the restarted loop's fresh bone is cut at once), until 300
        replies came after the outage (bounded: two minutes of waypoints)."""
        for k in range(120_000):
            if len(replies_after) >= 300:
                return
            a = 0.00075 * k
            yield Waypoint((13.0 + 4.0 * math.cos(a), 4.0 * math.sin(a), 1.5), rpm=60_000.0)

    mover = threading.Thread(target=restart, daemon=True)
    mover.start()
    try:
        with BurrClient(host, port, session=KEYED, key=KEY, timeout_s=2.0) as c:
            out = stream(c, waypoints(), 1000.0, on_result,
                         on_outage=lambda gone, i: events.append((gone, i)))
            counters = dict(c.counters)
    finally:
        mover.join(120.0)
        state["hot"].stop()
    assert out.outages == 1 and [gone for gone, _ in events] == [True, False]
    assert events[0][1] < events[1][1] and out.outage_ticks == events[1][1] - events[0][1]
    assert out.lost >= out.outage_ticks > 0
    assert counters["wrong_stream"] == 1 and counters["streams"] == 2
    assert replies_after[0].status & STATUS_STALE
    assert all(r.status & STATUS_CUTTING for r in replies_after[100:])


def test_every_valid_form_of_a_pose_gets_the_same_answer_and_oversized_none(server):
    """Through the real socket (received into the loop's own buffer): a POSE in a valid but
    non-canonical form (the general decoder's path) is answered as its canonical form is, and
    an oversized datagram is counted, never answered."""
    above = (0.0, 0.03, 0.005)  # unity metres: 30 mm above the workpiece, touching nothing
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(2.0)
    sock.connect(server.address)
    try:
        def pose(seq: int, stream: int) -> bytes:
            return encode_pose(Pose(OPEN, seq, 10**9 + 1000 * seq, above, (0.0, 0.0, 0.0, 1.0),
                                    60_000.0, True, None, 0, stream))

        sock.send(pose(1, 0))
        notice = decode_server_message(sock.recv(2048))
        assert isinstance(notice, Notice) and notice.error == NEW_STREAM
        sock.send(pose(2, notice.stream))  # commits the stream (its first tick is stale)
        first = decode_server_message(sock.recv(2048))
        canonical = pose(3, notice.stream)
        # The version as uint 8 (cc 02), the stream as uint 64: valid, not canonical.
        fields = msgpack.unpackb(pose(4, notice.stream))
        assert fields[11] == notice.stream and fields[12] is None
        variant = (b"\x9d\xcc\x02" + b"".join(msgpack.packb(x) for x in fields[1:11])
                   + b"\xcf" + notice.stream.to_bytes(8, "big") + b"\xc0")
        sock.send(canonical)
        r3 = decode_server_message(sock.recv(2048))
        sock.send(variant)
        r4 = decode_server_message(sock.recv(2048))
        before = server.stats()["counters"]["too_big"]
        sock.send(canonical[:-1] + bytes(600))
        deadline = time.monotonic() + 10.0
        while server.stats()["counters"]["too_big"] == before and time.monotonic() < deadline:
            time.sleep(0.01)
        assert server.stats()["counters"]["too_big"] == before + 1
    finally:
        sock.close()
    assert isinstance(first, Reply) and first.status & STATUS_STALE
    assert isinstance(r3, Reply) and isinstance(r4, Reply) and (r3.seq, r4.seq) == (3, 4)
    same = ("seq", "t_client_us", "t_recv_us", "t_send_us")
    assert r3._replace(**{k: 0 for k in same}) == r4._replace(**{k: 0 for k in same})
    assert r4.error == OK and not r4.status & STATUS_STALE


def test_a_spare_warms_at_the_lowest_priority_and_serves_at_the_loops():
    """A warming spare must not take CPU from loops already serving; once warm, and so once
    it may replace one, it runs at their priority (where raising it is allowed: as root)."""
    from burrforce.server.hotloop.child import HOT_LOOP_NICE, SPARE_WARMING_NICE

    hot = HotLoopProcess(HotLoopConfig(sessions=()))
    seen: set[int] = set()
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            try:
                seen.add(os.getpriority(os.PRIO_PROCESS, hot.pid))
            except (RuntimeError, OSError):  # not spawned yet, or gone
                pass
            time.sleep(0.002)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        hot.spawn_spare()
        done.set()
        watcher.join()
        final = os.getpriority(os.PRIO_PROCESS, hot.pid)
        if os.geteuid() == 0:
            assert SPARE_WARMING_NICE in seen, seen
            assert final == HOT_LOOP_NICE
        else:  # neither way is allowed: it keeps the usual priority throughout
            assert SPARE_WARMING_NICE not in seen and final == os.getpriority(
                os.PRIO_PROCESS, 0)
        hot.start()  # the spare takes a worker's place at that priority
        assert os.getpriority(os.PRIO_PROCESS, hot.pid) == final
    finally:
        done.set()
        watcher.join()
        hot.stop()
