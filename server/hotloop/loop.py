"""The socket side of the hot loop: one thread, one port, a socket per authenticated peer.

Flood isolation (measured, ``burrforce bench flood``): with a single socket, 83 000 junk
datagrams/s from one local sender filled its queue and the loop's time, and a keyed session at
1 kHz lost 15 % of its replies. So:

- The port's main socket takes everyone's first datagrams. Its work is capped at
  ``MAIN_BUDGET_HZ`` datagrams per second (a token bucket checked before anything is read):
  beyond that it is not read at all, the kernel drops what overflows its queue, and a flood
  costs the loop at most that budget.
- A peer whose POSE a session has accepted (authentic, in its stream) gets a socket of its own
  on the same port, ``connect()``-ed to it (``SO_REUSEPORT``: Linux gives a connected socket
  every datagram of its 4-tuple, ahead of the unconnected one). Junk, foreign and forged
  datagrams from anybody else never enter that socket's queue, and it is read first, always.
- Everything runs on one thread with ``epoll``: no GIL hand-offs between socket threads, which
  would make a busy main socket delay a session's packet by a switch interval (5 ms).

A client changes nothing: it sends to the same port and gets its replies from it.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import threading
import time
from collections.abc import Callable

from .bucket import TokenBucket
from .dispatch import Dispatcher
from .wake import DEFAULT_WAKE, WAKE_COUNTERS, WakeAhead, WakeConfig
from .wire import RX_BYTES

#: Read one byte more than a request may have, so an oversized datagram shows as such (the
#: kernel truncates it to the buffer) instead of arriving cut to a plausible length.
RECV_BYTES = RX_BYTES
#: Kernel receive buffer asked for, bytes: a few hundred ms of 1 kHz traffic from many sessions.
RCVBUF_BYTES = 1 << 20
#: A peer's own socket needs only a few packets of slack: it is read first.
PEER_RCVBUF_BYTES = 1 << 18
#: Datagrams per second the main socket (first contacts, junk) may cost the loop, and the
#: burst: a few hellos per session, and little enough of two cores that a flood's p99 stays
#: near the quiet one (``bench flood`` at 100 000/s: 0.9–4.5 × the quiet p99 with a budget
#: of 20 000/s, 0.7–2.1 × with 5 000/s; nothing lost with either).
MAIN_BUDGET_HZ = 5_000.0
MAIN_BURST = 500.0
#: Peers with a socket of their own, at most (the least recently active goes first).
MAX_PEERS = 64
#: select()'s descriptor limit (glibc's FD_SETSIZE).
FD_SETSIZE = 1024
#: A peer socket silent this long is closed (its client went away), s.
PEER_IDLE_S = 10.0
#: How often peers are reconciled with the sessions (removed sessions, idle peers), s.
HOUSEKEEPING_S = 0.5
#: The loop's own counters (in ``Dispatcher.counters``): times the main socket went unread
#: for being over budget; peers given a socket; sockets that could not be made; and waking
#: ahead (``hotloop.wake``).
LOOP_COUNTERS = ("main_deferred", "peers_adopted", "peer_socket_errors", *WAKE_COUNTERS)


def _bind(host: str, port: int, reuse: bool) -> socket.socket:
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        if reuse:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


def open_socket(host: str, port: int) -> socket.socket:
    """A UDP socket bound to (host, port), ready for peer sockets on the same port; port 0
    picks a free one.

    Raises:
        OSError: the address cannot be bound (in use, not a local address, …); the message
            says which and what to do.
    """
    try:
        # Bound first without SO_REUSEPORT: that fails if anybody (another burrforce serve)
        # holds the port, which joining a reuse group would not.
        probe = _bind(host, port, reuse=False)
        port = probe.getsockname()[1]
        probe.close()
        sock = _bind(host, port, reuse=True)
    except OSError as exc:
        hint = (" (is another burrforce serve running? --udp-port 0 picks a free port)"
                if exc.errno == errno.EADDRINUSE else "")
        raise OSError(exc.errno, f"cannot listen on UDP {host}:{port}: "
                                 f"{exc.strerror}{hint}") from None
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
    return sock


class PeerSockets:
    """The connected sockets of authenticated peers (``address → socket``), registered
    with the loop's epoll."""

    def __init__(self, main: socket.socket, poller: select.epoll,
                 counters: dict[str, int]) -> None:
        self.main = main
        self.counters = counters
        self.host, self.port = main.getsockname()[:2]
        self.poller = poller
        self.by_fd: dict[int, socket.socket] = {}
        self.by_peer: dict[object, socket.socket] = {}
        #: The address of each peer socket's peer (the dispatcher's ``peer``).
        self.peer_of: dict[int, object] = {}
        self.last_ns: dict[int, int] = {}
        #: Called with a peer socket's descriptor when it closes.
        self.on_close: Callable[[int], None] | None = None

    def adopt(self, peer: object, now_ns: int) -> None:
        """Give ``peer`` (whose POSE a session just accepted) a socket of its own."""
        if peer in self.by_peer:
            return
        if len(self.by_peer) >= MAX_PEERS:
            oldest = min(self.by_fd, key=self.last_ns.__getitem__)
            self.close(oldest)
        try:
            sock = _bind(self.host, self.port, reuse=True)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, PEER_RCVBUF_BYTES)
            sock.connect(peer)
            sock.setblocking(False)
        except OSError:  # out of descriptors, say: the main socket still serves the peer
            self.counters["peer_socket_errors"] += 1
            return
        self.counters["peers_adopted"] += 1
        fd = sock.fileno()
        self.by_fd[fd] = sock
        self.by_peer[peer] = sock
        self.peer_of[fd] = peer
        self.last_ns[fd] = now_ns
        self.poller.register(fd, select.EPOLLIN)

    def close(self, fd: int) -> None:
        sock = self.by_fd.pop(fd)
        self.last_ns.pop(fd, None)
        self.peer_of.pop(fd, None)
        if self.on_close is not None:
            self.on_close(fd)
        for peer, s in list(self.by_peer.items()):
            if s is sock:
                del self.by_peer[peer]
        try:
            self.poller.unregister(fd)
        except OSError:
            pass
        sock.close()

    def housekeeping(self, now_ns: int) -> None:
        """Close the sockets of peers that went quiet."""
        idle_ns = PEER_IDLE_S * 1e9
        for fd, last in list(self.last_ns.items()):
            if now_ns - last > idle_ns:
                self.close(fd)

    def close_all(self) -> None:
        for fd in list(self.by_fd):
            self.close(fd)


def _poll_ahead(poller: select.epoll, window: tuple[int, int], wake: WakeAhead,
                clock) -> list:
    """Wait for events as :class:`WakeAhead` planned: asleep until the window opens (or a
    datagram comes), then polling without sleeping until a datagram comes, the window
    closes, or another task turns out to hold the core (``hotloop.wake``)."""
    start, end = window
    now = clock()
    if start > now:
        # epoll_wait's timeout is whole milliseconds; select's on the epoll descriptor is µs.
        ready = select.select((poller,), (), (), (start - now) * 1e-9)[0]
        wake.woke(clock())
        if ready:
            wake.early()
            return poller.poll(0)
    t0 = clock()
    yield_cpu = os.sched_yield
    held_ns = wake.lead_ns
    while True:
        events = poller.poll(0)
        t = clock()
        if events or t >= end:
            break
        # A client on this core (the engine beside the server) sends first: the poll must not
        # delay the very packet it waits for.
        yield_cpu()
        back = clock()
        if back - t > held_ns:  # a task that does not block held the core: stop polling
            wake.preempted(back)
            events = poller.poll(0)
            t = back
            break
    wake.polled(t0, t, bool(events))
    return events


def serve(sock: socket.socket, dispatcher: Dispatcher, lock: threading.Lock,
          stopping: threading.Event, wake_config: WakeConfig = DEFAULT_WAKE) -> None:
    """Answer datagrams until ``stopping`` is set and the socket is shut down.

    ``lock`` is held while a datagram is handled, so commands (another thread) change
    sessions between packets, never during one. ``wake_config``: whether and how far the
    loop wakes ahead of its peers' predicted packets (``hotloop.wake``).
    """
    poller = select.epoll()
    main_fd = sock.fileno()
    poller.register(main_fd, select.EPOLLIN)
    counters = dispatcher.counters
    for name in LOOP_COUNTERS:
        counters.setdefault(name, 0)
    peers = PeerSockets(sock, poller, counters)
    by_fd = peers.by_fd
    peer_of = peers.peer_of
    last_ns = peers.last_ns
    clock = time.monotonic_ns
    # select() takes descriptors below FD_SETSIZE only: a loop whose epoll lies beyond
    # (a process with over a thousand files open) blocks as before.
    wake = (WakeAhead(wake_config, clock(), counters, os.cpu_count() or 1)
            if wake_config.enabled and poller.fileno() < FD_SETSIZE else None)
    if wake is not None:
        peers.on_close = wake.forget
    # Datagrams are received into the dispatcher's own buffer, and replies are slices of
    # its reply buffer: no bytes object per packet either way.
    handle = dispatcher.handle_received
    rx = dispatcher.rx_view
    budget = TokenBucket(MAIN_BUDGET_HZ, MAIN_BURST)
    main_on = True
    housekeeping_ns = clock()
    wait_s = -1.0
    try:
        while True:
            # Not while the main socket is deferred (a flood): its budget's timer decides.
            window = wake.next_poll(clock()) if wake is not None and wait_s < 0.0 else None
            try:
                events = (poller.poll(wait_s) if window is None
                          else _poll_ahead(poller, window, wake, clock))
            except InterruptedError:
                continue
            if stopping.is_set():
                return
            now = clock()
            if window is None and wake is not None:
                wake.woke(now)
            wait_s = -1.0
            main_ready = False
            for fd, _mask in events:
                if fd == main_fd:
                    main_ready = True
                    continue
                peer_sock = by_fd.get(fd)
                if peer_sock is None:
                    continue
                # Peers first. One datagram per event: epoll is level-triggered, so a queue
                # that holds more is reported again at once (no exception to end a batch).
                try:
                    n = peer_sock.recv_into(rx, RECV_BYTES)
                except OSError:  # ICMP from an earlier reply: the peer's port closed
                    continue
                t_recv = clock()
                with lock:
                    out = handle(n, t_recv, None, peer_of[fd])
                last_ns[fd] = t_recv
                if wake is not None:
                    wake.arrived(fd, t_recv)
                if out is not None:
                    try:
                        peer_sock.send(out)
                    except OSError:
                        counters["send_errors"] += 1
            if main_ready:
                if budget.take(now):
                    try:
                        n, addr = sock.recvfrom_into(rx, RECV_BYTES, socket.MSG_DONTWAIT)
                    except BlockingIOError:
                        n = addr = None
                    except OSError:  # shut down, or ICMP from an earlier reply
                        if stopping.is_set():
                            return
                        n = addr = None
                    if n is not None:
                        if addr is None:  # shutdown() wakes it with no sender
                            return
                        t_recv = clock()
                        with lock:
                            out = handle(n, t_recv, None, addr)
                            accepted = dispatcher.accepted
                        if out is not None:
                            try:
                                sock.sendto(out, addr)
                            except OSError:
                                counters["send_errors"] += 1
                        if accepted:
                            peers.adopt(addr, t_recv)
                elif main_on:
                    # Over budget: stop reading the main socket until a token is due; the
                    # kernel drops what overflows its queue, for free.
                    poller.modify(main_fd, 0)
                    main_on = False
                    counters["main_deferred"] += 1
            if not main_on:
                due_s = budget.due_s(clock())
                if due_s <= 0.0:
                    poller.modify(main_fd, select.EPOLLIN)
                    main_on = True
                else:
                    wait_s = due_s
            if now - housekeeping_ns > HOUSEKEEPING_S * 1e9:
                housekeeping_ns = now
                peers.housekeeping(now)
    finally:
        peers.close_all()
        poller.close()
        if wake is not None:
            wake.close()
