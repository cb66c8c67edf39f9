"""The asyncio UDP client: the same protocol as :class:`~.udp.BurrClient`, awaitable."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Sequence

from ..proto.messages import Notice
from .udp import IDENTITY, MAX_RESENDS, Result, ServerError, ServerGone, SessionRules, now_us

#: Unclaimed replies kept for :meth:`AsyncBurrClient.receive` (oldest dropped first).
QUEUE_LIMIT = 1024


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, owner: AsyncBurrClient) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.owner._arrived(data, now_us())

    def error_received(self, exc: Exception) -> None:  # ICMP errors: nothing listens
        self.owner._gone(exc)


class AsyncBurrClient:
    """An asyncio UDP client for one session. Create with :meth:`connect`.

    ``exchange`` awaits the reply to its own packet; replies nobody awaits are queued for
    :meth:`receive` (at most QUEUE_LIMIT). Tags, staleness, the stream handshake and counters
    as ``BurrClient``; so is :class:`ServerGone`: when nothing listens on the server's port,
    pending exchanges and the next :meth:`send` or :meth:`receive` raise it (``icmp_errors``
    counts the operating system's reports).
    """

    def __init__(self, session: int, key: bytes | str | None, timeout_s: float,
                 first_seq: int, host: str = "", port: int = 0) -> None:
        self.rules = SessionRules(session, key, first_seq)
        self.counters = self.rules.counters
        self.counters["icmp_errors"] = 0
        self.timeout_s = timeout_s
        self.host = host
        self.port = port
        #: A "port unreachable" not yet reported to the caller.
        self._gone_pending = False
        self._waiting: dict[int, asyncio.Future] = {}
        self._queue: deque[Result | Notice] = deque(maxlen=QUEUE_LIMIT)
        self._queued = asyncio.Event()
        self._transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def connect(cls, host: str, port: int, session: int = 1,
                      key: bytes | str | None = None, timeout_s: float = 0.1,
                      first_seq: int = 1) -> AsyncBurrClient:
        client = cls(session, key, timeout_s, first_seq, host, port)
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Protocol(client), remote_addr=(host, port))
        client._transport = transport  # type: ignore[assignment]
        return client

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()
        for future in self._waiting.values():
            if not future.done():
                future.cancel()

    async def __aenter__(self) -> AsyncBurrClient:
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.close()

    def send(self, position: Sequence[float], orientation: Sequence[float] = IDENTITY,
             rpm: float = 0.0, spindle_on: bool = True,
             velocity: Sequence[float] | None = None, flags: int = 0,
             t_us: int | None = None) -> int:
        """Send one pose (as :meth:`BurrClient.send`); returns its sequence number.

        Raises:
            ServerGone: an earlier datagram found nothing listening on the server's port.
        """
        if self._transport is None:
            raise RuntimeError("not connected: use await AsyncBurrClient.connect(...)")
        self._raise_if_gone()
        seq, datagram = self.rules.datagram(position, orientation, rpm, spindle_on, velocity,
                                            flags, t_us)
        self._transport.sendto(datagram)
        return seq

    def _gone(self, exc: Exception) -> None:
        if not isinstance(exc, ConnectionRefusedError):
            return
        self.counters["icmp_errors"] += 1
        gone = ServerGone(self.host, self.port)
        waiting = [f for f in self._waiting.values() if not f.done()]
        for future in waiting:
            future.set_exception(gone)
        # Reported once: to the exchanges waiting, else to the next send or receive.
        self._gone_pending = not waiting
        self._queued.set()

    def _raise_if_gone(self) -> None:
        if self._gone_pending:
            self._gone_pending = False
            raise ServerGone(self.host, self.port)

    def _arrived(self, data: bytes, arrived_us: int) -> None:
        self._gone_pending = False  # the server answers: whatever went before is over
        item = self.rules.accept(data, arrived_us)
        if item is None:
            return
        seq = item.seq if isinstance(item, Notice) else item.reply.seq
        future = self._waiting.pop(seq, None)
        if future is not None and not future.done():
            future.set_result(item)
            return
        self._queue.append(item)
        self._queued.set()

    async def receive(self, timeout_s: float | None = None) -> Result | Notice | None:
        """The next reply or notice nobody awaited, or None after the timeout.

        Raises:
            ServerGone: nothing listens on the server's port (reported once).
        """
        loop = asyncio.get_running_loop()
        deadline = loop.time() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            self._raise_if_gone()
            if self._queue:
                return self._queue.popleft()
            self._queued.clear()
            try:
                await asyncio.wait_for(self._queued.wait(), max(deadline - loop.time(), 0.0))
            except asyncio.TimeoutError:
                return None

    async def exchange(self, position: Sequence[float],
                       orientation: Sequence[float] = IDENTITY, rpm: float = 0.0,
                       spindle_on: bool = True, velocity: Sequence[float] | None = None,
                       flags: int = 0, timeout_s: float | None = None) -> Result:
        """Send a pose and await its reply; through the stream handshake as
        :meth:`BurrClient.exchange` (``timeout_s`` per send).

        Raises:
            TimeoutError: no reply within the timeout.
            ServerError: a notice or an error reply.
            ServerGone: nothing listens on the server's port.
        """
        wait = self.timeout_s if timeout_s is None else timeout_s
        for _ in range(MAX_RESENDS + 1):
            future = asyncio.get_running_loop().create_future()
            seq = self.send(position, orientation, rpm, spindle_on, velocity, flags)
            self._waiting[seq] = future
            try:
                item = await asyncio.wait_for(future, wait)
            except asyncio.TimeoutError:
                self.counters["timeouts"] += 1
                raise TimeoutError(f"no reply to packet {seq} within {wait:g} s") from None
            finally:
                self._waiting.pop(seq, None)
            result = SessionRules.answer_to(item, seq)
            # The future of ``seq`` only ever gets ``seq``'s answer.
            if isinstance(result, Result):
                return result
        raise ServerError(item.error, seq)
