"""The socket side of the hot loop: one blocking UDP socket, one thread, nothing else per packet."""

from __future__ import annotations

import errno
import socket
import threading
import time

from ...proto.messages import MAX_REQUEST_BYTES
from .dispatch import Dispatcher

#: Read one byte more than a request may have, so an oversized datagram shows as such (the
#: kernel truncates it to the buffer) instead of arriving cut to a plausible length.
RECV_BYTES = MAX_REQUEST_BYTES + 1
#: Kernel receive buffer asked for, bytes: a few hundred ms of 1 kHz traffic from many sessions.
RCVBUF_BYTES = 1 << 20


def open_socket(host: str, port: int) -> socket.socket:
    """A blocking UDP socket bound to (host, port); port 0 picks a free one.

    Raises:
        OSError: the address cannot be bound (in use, not a local address, …); the message
            says which and what to do.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        hint = (" (is another burrforce serve running? --udp-port 0 picks a free port)"
                if exc.errno == errno.EADDRINUSE else "")
        raise OSError(exc.errno, f"cannot listen on UDP {host}:{port}: "
                                 f"{exc.strerror}{hint}") from None
    return sock


def serve(sock: socket.socket, dispatcher: Dispatcher, lock: threading.Lock,
          stopping: threading.Event) -> None:
    """Answer datagrams until ``stopping`` is set and the socket is shut down.

    ``lock`` is held while a datagram is handled, so commands (another thread) change
    sessions between packets, never during one.
    """
    recv = sock.recvfrom
    send = sock.sendto
    clock = time.monotonic_ns
    handle = dispatcher.handle
    counters = dispatcher.counters
    while True:
        try:
            data, addr = recv(RECV_BYTES)
        except OSError:  # e.g. ICMP "port unreachable" from an earlier reply; or shut down
            if stopping.is_set():
                return
            continue
        if addr is None or stopping.is_set():  # shutdown() wakes recvfrom with no sender
            return
        t_recv = clock()
        with lock:
            out = handle(data, t_recv)
        if out is not None:
            try:
                send(out, addr)
            except OSError:
                counters["send_errors"] += 1
