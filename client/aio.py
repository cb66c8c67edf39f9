"""The asyncio UDP client: the same protocol as :class:`~.udp.BurrClient`, awaitable."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Sequence

from ..proto.messages import Notice
from .udp import IDENTITY, Result, SessionRules, now_us

#: Unclaimed replies kept for :meth:`AsyncBurrClient.receive` (oldest dropped first).
QUEUE_LIMIT = 1024


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, owner: AsyncBurrClient) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: object) -> None:
        self.owner._arrived(data, now_us())

    def error_received(self, exc: Exception) -> None:  # ICMP errors: nothing listens yet
        self.owner.counters["icmp_errors"] = self.owner.counters.get("icmp_errors", 0) + 1


class AsyncBurrClient:
    """An asyncio UDP client for one session. Create with :meth:`connect`.

    ``exchange`` awaits the reply to its own packet; replies nobody awaits are queued for
    :meth:`receive` (at most QUEUE_LIMIT). Tags, staleness and counters as ``BurrClient``.
    """

    def __init__(self, session: int, key: bytes | str | None, timeout_s: float,
                 first_seq: int) -> None:
        self.rules = SessionRules(session, key, first_seq)
        self.counters = self.rules.counters
        self.timeout_s = timeout_s
        self._waiting: dict[int, asyncio.Future] = {}
        self._queue: deque[Result | Notice] = deque(maxlen=QUEUE_LIMIT)
        self._queued = asyncio.Event()
        self._transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def connect(cls, host: str, port: int, session: int = 1,
                      key: bytes | str | None = None, timeout_s: float = 0.1,
                      first_seq: int = 1) -> AsyncBurrClient:
        client = cls(session, key, timeout_s, first_seq)
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
        if self._transport is None:
            raise RuntimeError("not connected: use await AsyncBurrClient.connect(...)")
        seq, datagram = self.rules.datagram(position, orientation, rpm, spindle_on, velocity,
                                            flags, t_us)
        self._transport.sendto(datagram)
        return seq

    def _arrived(self, data: bytes, arrived_us: int) -> None:
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
        """The next reply or notice nobody awaited, or None after the timeout."""
        if not self._queue:
            self._queued.clear()
            try:
                await asyncio.wait_for(self._queued.wait(),
                                       self.timeout_s if timeout_s is None else timeout_s)
            except asyncio.TimeoutError:
                return None
        return self._queue.popleft()

    async def exchange(self, position: Sequence[float],
                       orientation: Sequence[float] = IDENTITY, rpm: float = 0.0,
                       spindle_on: bool = True, velocity: Sequence[float] | None = None,
                       flags: int = 0, timeout_s: float | None = None) -> Result:
        """Send a pose and await its reply.

        Raises:
            TimeoutError: no reply within the timeout.
            ServerError: a notice or an error reply.
        """
        future = asyncio.get_running_loop().create_future()
        seq = self.send(position, orientation, rpm, spindle_on, velocity, flags)
        self._waiting[seq] = future
        wait = self.timeout_s if timeout_s is None else timeout_s
        try:
            item = await asyncio.wait_for(future, wait)
        except asyncio.TimeoutError:
            self.counters["timeouts"] += 1
            raise TimeoutError(f"no reply to packet {seq} within {wait:g} s") from None
        finally:
            self._waiting.pop(seq, None)
        result = SessionRules.answer_to(item, seq)
        assert result is not None  # the future of ``seq`` only ever gets ``seq``'s answer
        return result
