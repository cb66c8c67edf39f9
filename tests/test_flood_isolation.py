"""A keyed session keeps every reply while strangers flood its port (hotloop.loop): its peer
gets a socket of its own, the main socket's work is capped. Real hot loop, real UDP on
127.0.0.1; the flood is bounded in count. Round-trip numbers are ``bench flood``'s job."""

from __future__ import annotations

import multiprocessing
import socket
import time

import pytest

from burrforce.client.udp import BurrClient
from burrforce.server.bench.flood import _payloads
from burrforce.server.hotloop import HotLoopConfig, HotLoopProcess, SessionSpec
from burrforce.server.hotloop.loop import MAIN_BUDGET_HZ, MAIN_BURST, open_socket

KEY = bytes(range(32))
SESSION = 3
FLOOD_DATAGRAMS = 60_000


def _flood(host: str, port: int, kind: str, senders: int, count: int) -> None:
    payloads = _payloads(kind, SESSION)
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(senders)]
    for n in range(count):
        try:
            socks[n % senders].sendto(payloads[n % len(payloads)], (host, port))
        except OSError:
            pass


def _wait_until_drained(server, counter: str) -> None:
    """Wait until the main socket's queue holds no more of the flood: the kernel dropped what
    did not fit, but the queue is still full when the flood ends, and it drains at the
    budget's rate (~0.5 s). A hello sent before would be dropped as the flood was: a test
    that came next would wait for a reply that cannot come."""
    quiet_s = 1000 / MAIN_BUDGET_HZ  # a thousand datagrams' worth of budget, unread
    deadline = time.monotonic() + 30.0
    last = server.stats()["counters"][counter]
    while time.monotonic() < deadline:
        time.sleep(quiet_s)
        now = server.stats()["counters"][counter]
        if now == last:
            return
        last = now
    raise AssertionError(f"the flood was still being read after 30 s ({counter} = {last})")


@pytest.fixture(scope="module")
def server():
    config = HotLoopConfig(sessions=(SessionSpec(SESSION, "phantom:workpiece", 0.5, KEY),))
    with HotLoopProcess(config) as hot:
        yield hot


@pytest.mark.parametrize("kind,senders", [("junk", 1), ("foreign", 8), ("unknown", 32)])
def test_a_streaming_session_loses_nothing_while_its_port_is_flooded(server, kind, senders):
    before = server.stats()["counters"]
    with BurrClient(*server.address, session=SESSION, key=KEY, timeout_s=2.0) as client:
        client.exchange((5.0, 0.0, 5.0))  # the stream is open: the peer has its socket
        ctx = multiprocessing.get_context("spawn")
        t0 = time.monotonic()
        flooder = ctx.Process(target=_flood, args=(*server.address, kind, senders,
                                                   FLOOD_DATAGRAMS))
        flooder.start()
        replies = 0
        while flooder.is_alive() or replies < 200:
            client.exchange((5.0, 0.0, 5.0))  # raises TimeoutError if a reply is lost
            replies += 1
        flooder.join(60)
    after = server.stats()["counters"]
    elapsed_s = time.monotonic() - t0
    refused = {"junk": "malformed", "foreign": "bad_tag", "unknown": "unknown_session"}[kind]
    _wait_until_drained(server, refused)
    assert after[refused] > before[refused]  # the flood reached the server
    # The main socket read no more than its budget allows over the time it ran (however long
    # a busy machine made that): the rest of the flood never cost the loop anything.
    assert after[refused] - before[refused] <= MAIN_BURST + MAIN_BUDGET_HZ * elapsed_s
    assert client.counters["timeouts"] == 0


def test_each_peer_gets_its_own_socket_once_it_is_accepted(server):
    """Two engines on one session (open at once, so on two ports): each is adopted when its
    stream is accepted, and both keep being answered."""
    before = server.stats()["counters"]["peers_adopted"]
    with BurrClient(*server.address, session=SESSION, key=KEY, timeout_s=2.0) as a, \
            BurrClient(*server.address, session=SESSION, key=KEY, timeout_s=2.0) as b:
        a.exchange((5.0, 0.0, 5.0))
        b.exchange((5.0, 0.0, 5.0))
        assert server.stats()["counters"]["peers_adopted"] == before + 2


def test_a_forged_datagram_from_a_stranger_gives_it_no_socket(server):
    before = server.stats()["counters"]
    _flood(*server.address, "foreign", 1, 50)
    with BurrClient(*server.address, session=SESSION, key=KEY, timeout_s=2.0) as client:
        client.exchange((5.0, 0.0, 5.0))  # a fence: the forged ones were read before
    after = server.stats()["counters"]
    assert after["bad_tag"] >= before["bad_tag"] + 1
    # The client's at most (a port the kernel hands out again may still have its socket).
    assert after["peers_adopted"] <= before["peers_adopted"] + 1


def test_a_second_server_on_the_same_port_is_refused():
    first = open_socket("127.0.0.1", 0)
    try:
        port = first.getsockname()[1]
        with pytest.raises(OSError, match="another burrforce serve"):
            open_socket("127.0.0.1", port)
    finally:
        first.close()
