"""stream() through a server that stops and starts again on its port: the outages it counts.

The server is scripted on a real UDP socket of 127.0.0.1 and answers only between the
stream's sends (from the waypoints' generator, which stream() runs between sends): every step
happens in the order the script says. Each stop and start also waits for what the client has
seen (read, or said), so a client that this machine runs late still meets every step.
Bounded: LIMIT waypoints at 1 kHz.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

from burrforce.client import BurrClient, Result, StreamResult, Waypoint, stream
from burrforce.proto.codec import decode_pose, encode_notice, encode_reply
from burrforce.proto.messages import HELLO_STREAM, NEW_STREAM, OK, WRONG_STREAM, Notice, Reply

RATE_HZ = 1000.0
SESSION = 7
#: How long the server's host keeps the client from running as the server stops, s: the
#: client is then this far behind its schedule and sends without reading until it catches up.
STALL_S = 0.03
#: Waypoints the server is up for (after the client said it is back), and down for (after
#: the client read every answer it sent); LIMIT: waypoints at most (20 s).
UP, DOWN, LIMIT = 50, 20, 20_000
ZERO3 = (0.0, 0.0, 0.0)


class ScriptedServer:
    """The stream handshake and a reply to every pose of its stream (SPEC.md 5.2), for an
    unkeyed session, answered when :meth:`answer` is called. Each :meth:`start` on the same
    port is a restarted server: a new stream, and the old one is answered WRONG_STREAM."""

    def __init__(self) -> None:
        self.port = 0
        self.stream = HELLO_STREAM
        self.sock: socket.socket | None = None
        #: Datagrams sent, by every start of the server.
        self.sent = 0
        self.start()

    def start(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind(("127.0.0.1", self.port))
        sock.setblocking(False)
        self.sock, self.port = sock, sock.getsockname()[1]
        self.stream += 1

    def stop(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    def answer(self) -> None:
        """Answer every pose that has arrived."""
        assert self.sock is not None
        while True:
            try:
                data, peer = self.sock.recvfrom(4096)
            except BlockingIOError:
                return
            pose = decode_pose(data)
            if pose.stream == HELLO_STREAM:
                out = encode_notice(Notice(pose.session, pose.seq, pose.t_client_us,
                                           NEW_STREAM, self.stream))
            elif pose.stream != self.stream:
                out = encode_notice(Notice(pose.session, pose.seq, pose.t_client_us,
                                           WRONG_STREAM, pose.stream))
            else:
                now_us = time.monotonic_ns() // 1000
                out = encode_reply(Reply(pose.session, pose.seq, pose.t_client_us, now_us,
                                         now_us, OK, 0, ZERO3, ZERO3, ZERO3, 0.0, 0.0, 0.0,
                                         ZERO3, ZERO3, ZERO3, 0.0, 0.0, 0.0, 0, ZERO3))
            self.sock.sendto(out, peer)
            self.sent += 1


def scripted(server: ScriptedServer, client: BurrClient, outages: int,
             events: list[tuple[bool, int]]) -> Iterator[Waypoint]:
    """Waypoints, the server answering what has arrived before each, through ``outages``
    stops and starts. A stop comes UP waypoints after the start (the first) or after the
    client said the server is back: it answers what has arrived (those answers are on their
    way back), closes the port and holds the client up for STALL_S. The start comes once the
    client has read every answer and sent DOWN more waypoints to the closed port. The
    waypoints end UP after the client said the server is back from the last stop, or at
    LIMIT."""
    k = 0
    for n in range(outages + 1):
        up_since = None
        while k < LIMIT:
            if up_since is None and sum(not gone for gone, _ in events) >= n:
                up_since = k
            if up_since is not None and k - up_since >= UP:
                break
            server.answer()
            yield waypoint(k)
            k += 1
        if n == outages:
            break
        server.answer()
        server.stop()
        time.sleep(STALL_S)
        read_at = None
        while k < LIMIT:
            if read_at is None and client.counters["received"] >= server.sent:
                read_at = k
            if read_at is not None and k - read_at >= DOWN:
                break
            yield waypoint(k)
            k += 1
        server.start()
    server.answer()  # the last pose


def waypoint(k: int) -> Waypoint:
    return Waypoint((5.0, 0.0, 30.0 + 0.001 * k))


def run(outages: int) -> tuple[StreamResult, list[tuple[bool, int]], dict[int, bool]]:
    """The stream through ``outages`` stops and starts; returns its result, the
    ``on_outage`` calls, and for each result whether it was read during an outage."""
    server = ScriptedServer()
    events: list[tuple[bool, int]] = []
    read_while_gone: dict[int, bool] = {}

    def on_result(i: int, result: Result) -> None:
        read_while_gone[i] = bool(events) and events[-1][0]

    try:
        with BurrClient("127.0.0.1", server.port, session=SESSION, timeout_s=1.0) as client:
            # The handshake first: every pose streamed before the first stop is then answered
            # with a reply, however late this machine runs the client.
            client.send((5.0, 0.0, 30.0))
            server.answer()
            assert isinstance(client.receive(), Notice) and client.counters["streams"] == 1
            out = stream(client, scripted(server, client, outages, events), RATE_HZ,
                         on_result, on_outage=lambda gone, i: events.append((gone, i)))
    finally:
        server.stop()
    return out, events, read_while_gone


def test_one_restart_is_one_outage_though_the_old_servers_last_reply_is_read_after_it():
    """The server answers pose UP - 1, then stops while the client is held up: the client,
    behind its schedule, sends without reading, and its socket reports the port's refusal
    ahead of that reply, which had arrived before it. The reply is a result but not the
    server answering again: one restart is one outage, over when the restarted server
    answers."""
    out, events, read_while_gone = run(1)
    assert out.outages == 1 and [gone for gone, _ in events] == [True, False], events
    at = [i for _, i in events]
    assert UP <= at[0] < at[1] and out.outage_ticks == at[1] - at[0]
    assert out.results[UP - 1] is not None and read_while_gone[UP - 1]


def test_a_second_stop_after_the_server_answered_again_is_a_second_outage():
    out, events, read_while_gone = run(2)
    assert out.outages == 2 and [gone for gone, _ in events] == [True, False, True, False], \
        events
    at = [i for _, i in events]
    assert UP <= at[0] < at[1] < at[2] < at[3]
    assert out.outage_ticks == (at[1] - at[0]) + (at[3] - at[2])
    assert out.results[UP - 1] is not None and read_while_gone[UP - 1]
