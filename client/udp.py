"""The UDP client: send poses, get decoded, verified replies with their round-trip time."""

from __future__ import annotations

import socket
import time
from collections.abc import Sequence
from typing import NamedTuple

from ..proto.codec import ProtocolError, decode_server_message, encode_pose
from ..proto.messages import (
    ERROR_NAMES,
    FLAG_NEW_STREAM,
    MAX_REPLY_BYTES,
    OK,
    Notice,
    Pose,
    Reply,
)
from ..proto.sequence import seq_after, seq_next
from ..proto.tag import Tagger, parse_key

IDENTITY = (0.0, 0.0, 0.0, 1.0)


class Result(NamedTuple):
    """A reply and what the client measured about it.

    Attributes:
        reply: the decoded reply.
        rtt_us: round trip, µs: from the request's timestamp to the reply's arrival (before
            decoding).
        offset_us: the server clock minus the client clock, µs (NTP's estimate: exact when
            the two directions take equally long).
    """

    reply: Reply
    rtt_us: float
    offset_us: float


class ServerError(RuntimeError):
    """The server answered with a notice (the request was not processed) or an error reply."""

    def __init__(self, code: int, seq: int) -> None:
        self.code = code
        self.seq = seq
        super().__init__(f"server refused packet {seq}: {ERROR_NAMES.get(code, code)}"
                         + _HINTS.get(code, ""))


_HINTS = {
    5: " (no such session: check --session, or that the server was restarted)",
    6: " (wrong or missing key: use the key the server printed)",
    3: " (protocol version mismatch: update the client or the server)",
    7: " (a value is unusable: NaN, infinite, or a quaternion that is not unit length)",
}


def now_us() -> int:
    """The client's monotonic clock, µs (what goes into t_client_us)."""
    return time.monotonic_ns() // 1000


class SessionRules:
    """What both clients do for one session, without I/O: number and tag outgoing POSEs, and
    decide which incoming datagrams to believe.

    Replies whose tag does not verify, that are not well-formed, that belong to another
    session, or that are older than one already accepted are dropped and counted in
    ``counters`` (``bad_tag``, ``malformed``, ``foreign``, ``stale``).
    """

    def __init__(self, session: int, key: bytes | str | None, first_seq: int) -> None:
        if isinstance(key, str):
            key = parse_key(key)
        self.session = session
        self.tagger = Tagger(key) if key else None
        self.seq = first_seq % (1 << 32)
        self.newest: int | None = None
        self.counters = {"sent": 0, "received": 0, "bad_tag": 0, "malformed": 0, "stale": 0,
                         "notices": 0, "timeouts": 0, "foreign": 0}

    def datagram(self, position: Sequence[float], orientation: Sequence[float], rpm: float,
                 spindle_on: bool, velocity: Sequence[float] | None, flags: int,
                 t_us: int | None) -> tuple[int, bytes]:
        """(seq, encoded POSE): the next sequence number, NEW_STREAM until the server has
        answered (so a restarted client is not taken for a replay of the old one)."""
        seq = self.seq
        self.seq = seq_next(seq)
        if self.newest is None:
            flags |= FLAG_NEW_STREAM
        pose = Pose(self.session, seq, now_us() if t_us is None else t_us,
                    tuple(position), tuple(orientation), rpm, spindle_on,  # type: ignore[arg-type]
                    None if velocity is None else tuple(velocity), flags)  # type: ignore[arg-type]
        self.counters["sent"] += 1
        return seq, encode_pose(pose, self.tagger)

    def accept(self, data: bytes, arrived_us: int) -> Result | Notice | None:
        """The datagram (arrived at ``arrived_us``) as a Result or Notice, or None if it is
        not to be believed."""
        try:
            message = decode_server_message(data)
        except ProtocolError:
            self.counters["malformed"] += 1
            return None
        if self.tagger is not None and isinstance(message, Reply) and (
                message.tag is None or not self.tagger.verify(data)):
            # Replies of a keyed session are always tagged: anything else is forged or
            # corrupt. Notices are passed on unverified: they carry no force, and one that
            # says BAD_TAG is tagged with the server's key, which a client with the wrong key
            # cannot check — yet it must learn that its key is wrong.
            self.counters["bad_tag"] += 1
            return None
        if message.session != self.session:
            self.counters["foreign"] += 1
            return None
        self.counters["received"] += 1
        if isinstance(message, Notice):
            self.counters["notices"] += 1
            return message
        if self.newest is not None and not seq_after(message.seq, self.newest):
            self.counters["stale"] += 1
            return None
        self.newest = message.seq
        offset = ((message.t_recv_us - message.t_client_us)
                  + (message.t_send_us - arrived_us)) / 2.0
        return Result(message, float(arrived_us - message.t_client_us), offset)

    @staticmethod
    def answer_to(item: Result | Notice, seq: int) -> Result | None:
        """``item`` if it answers packet ``seq`` (None if it answers another).

        Raises:
            ServerError: it answers ``seq`` with a notice or an error reply.
        """
        if isinstance(item, Notice):
            if item.seq == seq:
                raise ServerError(item.error, seq)
            return None
        if item.reply.seq != seq:
            return None
        if item.reply.error != OK:
            raise ServerError(item.reply.error, seq)
        return item


class BurrClient:
    """A UDP client for one session.

    Args:
        host, port: the server's UDP endpoint.
        session: the session id.
        key: the session key (bytes or hex), or None for a session without one.
        timeout_s: how long :meth:`exchange` waits for a reply.
        first_seq: the first sequence number (the server accepts any number to start a
            stream, and again after the session has been idle for a second).

    Replies are checked as ``SessionRules`` says; ``counters`` counts what was sent,
    received and dropped.
    """

    def __init__(self, host: str, port: int, session: int = 1, key: bytes | str | None = None,
                 timeout_s: float = 0.1, first_seq: int = 1) -> None:
        self.rules = SessionRules(session, key, first_seq)
        self.counters = self.rules.counters
        self.timeout_s = timeout_s
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self.sock = socket.socket(family, socket.SOCK_DGRAM)
        # connect(): the kernel then delivers only the server's datagrams to this socket.
        self.sock.connect((host, port))

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> BurrClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def send(self, position: Sequence[float], orientation: Sequence[float] = IDENTITY,
             rpm: float = 0.0, spindle_on: bool = True,
             velocity: Sequence[float] | None = None, flags: int = 0,
             t_us: int | None = None) -> int:
        """Send one pose (engine frame and units); returns its sequence number.

        ``t_us`` is when the pose was sampled, on :func:`now_us`'s clock (default: now). The
        server estimates velocity from these stamps, so a pose sent late must still carry
        its own time; the reply's round trip then counts from the sample, not the send.
        """
        seq, datagram = self.rules.datagram(position, orientation, rpm, spindle_on, velocity,
                                            flags, t_us)
        self.sock.send(datagram)
        return seq

    def receive(self, timeout_s: float | None = None) -> Result | Notice | None:
        """The next verified reply or notice, or None if none arrives within the timeout
        (0: only what has already arrived)."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            self.sock.settimeout(max(remaining, 0.0))
            try:
                data = self.sock.recv(MAX_REPLY_BYTES + 1)
            except (BlockingIOError, TimeoutError):
                return None
            except ConnectionRefusedError:  # ICMP: nothing listens on the server's port
                if remaining <= 0.0:
                    return None
                continue
            message = self.rules.accept(data, now_us())
            if message is not None:
                return message

    def exchange(self, position: Sequence[float], orientation: Sequence[float] = IDENTITY,
                 rpm: float = 0.0, spindle_on: bool = True,
                 velocity: Sequence[float] | None = None, flags: int = 0,
                 timeout_s: float | None = None) -> Result:
        """Send a pose and wait for its reply.

        Raises:
            TimeoutError: no reply within the timeout.
            ServerError: the server answered with a notice or an error reply.
        """
        seq = self.send(position, orientation, rpm, spindle_on, velocity, flags)
        wait = self.timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + wait
        while True:
            message = self.receive(max(deadline - time.monotonic(), 0.0))
            if message is None:
                self.counters["timeouts"] += 1
                raise TimeoutError(f"no reply to packet {seq} within {wait:g} s")
            result = SessionRules.answer_to(message, seq)
            if result is not None:
                return result
