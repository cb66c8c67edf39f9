"""The UDP client: send poses, get decoded, verified replies with their round-trip time.

The client opens its stream itself (SPEC.md 5.2): while it has none, every POSE it sends is
a hello; the server's verified NEW_STREAM notice gives it one, a verified WRONG_STREAM notice
takes it away again (the stream ended: REST restart-stream, or a server restart).
"""

from __future__ import annotations

import socket
import time
from collections.abc import Sequence
from typing import NamedTuple

from ..proto.codec import ProtocolError, decode_server_message, encode_pose
from ..proto.messages import (
    ERROR_NAMES,
    HELLO_STREAM,
    MAX_REPLY_BYTES,
    NEW_STREAM,
    OK,
    SEQ_MODULUS,
    WRONG_STREAM,
    Notice,
    Pose,
    Reply,
)
from ..proto.sequence import seq_after, seq_next
from ..proto.tag import Tagger, parse_key

IDENTITY = (0.0, 0.0, 0.0, 1.0)
#: The notices of the stream handshake: they answer a POSE that was not ticked, and the pose
#: is to be sent again (in the new stream, or as a hello).
HANDSHAKE_NOTICES = (NEW_STREAM, WRONG_STREAM)
#: How often :meth:`BurrClient.exchange` sends one pose again through the handshake
#: (WRONG_STREAM → hello → NEW_STREAM → the pose: two; one spare for a race).
MAX_RESENDS = 3
#: Hellos remembered (seq → t_client_us) to match a NEW_STREAM against: a second at 1 kHz.
HELLOS_KEPT = 1024


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
    11: " (the stream handshake did not settle: is another client using this session?)",
    12: " (the stream handshake did not settle: is another client using this session?)",
}


class StreamTaken(RuntimeError):
    """The server gave the session's stream to another client, and this one gives way
    (``give_way``) instead of saying hello and taking it back.

    Attributes:
        session: the session id.
    """

    def __init__(self, session: int) -> None:
        self.session = session
        super().__init__(f"another client took session {session}'s stream (the server "
                         "answered WRONG_STREAM); this client gave way")


class ServerGone(ConnectionError):
    """Nothing listens on the server's UDP port any more (the operating system said so: an
    ICMP "port unreachable" came back). The server stopped or restarted; a client that keeps
    sending finds it again when it is back (it then says hello and streams on).

    Attributes:
        host, port: the server's UDP endpoint.
    """

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port
        super().__init__(f"the burrforce server at {host}:{port} is gone: nothing listens on "
                         "its UDP port. Is `burrforce serve` running? (GET /v1/health on its "
                         "REST port answers while it runs)")


def now_us() -> int:
    """The client's monotonic clock, µs (what goes into t_client_us)."""
    return time.monotonic_ns() // 1000


class SessionRules:
    """What every client does for one session, without I/O: number, tag and put its stream
    into outgoing POSEs, run the stream handshake, and decide which incoming datagrams to
    believe.

    ``stream`` is the client's stream (0: none yet; every POSE is then a hello). Replies
    whose tag does not verify, that are not well-formed, that belong to another session, or
    that are older than one already accepted are dropped and counted in ``counters``
    (``bad_tag``, ``malformed``, ``foreign``, ``stale``); so are NEW_STREAM and WRONG_STREAM
    notices that do not verify. ``hellos`` counts hellos sent, ``streams`` streams adopted,
    ``wrong_stream`` streams the server ended.

    A session has one stream: a client's hello takes it from whoever held it, whose next POSE
    is answered WRONG_STREAM. Such a client says hello again and takes it back, unless
    ``give_way``: then its next POSE raises :class:`StreamTaken` instead (a background client
    that must not fight a person's: two clients taking the stream back and forth both lose
    most of their packets). A server that restarted also ends the stream.
    """

    def __init__(self, session: int, key: bytes | str | None, first_seq: int,
                 give_way: bool = False) -> None:
        if isinstance(key, str):
            key = parse_key(key)
        self.session = session
        self.tagger = Tagger(key) if key else None
        self.seq = first_seq % SEQ_MODULUS
        self.newest: int | None = None
        self.stream = HELLO_STREAM
        self.give_way = give_way
        #: The hellos sent since ``stream`` became 0 (the last HELLOS_KEPT): seq →
        #: t_client_us. A NEW_STREAM is taken only if it echoes one of them, seq and
        #: timestamp: an old one replayed to a client that restarted its seqs echoes a seq it
        #: may have sent again, never with the same timestamp (SPEC.md 5.2).
        self._hellos: dict[int, int] = {}
        self.counters = {"sent": 0, "received": 0, "bad_tag": 0, "malformed": 0, "stale": 0,
                         "notices": 0, "timeouts": 0, "foreign": 0, "hellos": 0,
                         "streams": 0, "wrong_stream": 0}

    def datagram(self, position: Sequence[float], orientation: Sequence[float], rpm: float,
                 spindle_on: bool, velocity: Sequence[float] | None, flags: int,
                 t_us: int | None) -> tuple[int, bytes]:
        """(seq, encoded POSE): the next sequence number, in the client's stream, or a hello
        (stream 0: the server answers NEW_STREAM and does not tick it) while it has none.

        Raises:
            StreamTaken: ``give_way``, and the server ended this client's stream.
        """
        if self.give_way and self.stream == HELLO_STREAM and self.counters["wrong_stream"]:
            raise StreamTaken(self.session)
        seq = self.seq
        self.seq = seq_next(seq)
        t_us = now_us() if t_us is None else t_us
        if self.stream == HELLO_STREAM:
            hellos = self._hellos
            hellos.pop(seq, None)  # re-inserted last: the dict stays oldest first
            hellos[seq] = t_us
            if len(hellos) > HELLOS_KEPT:
                del hellos[next(iter(hellos))]
            self.counters["hellos"] += 1
        pose = Pose(self.session, seq, t_us,
                    tuple(position), tuple(orientation), rpm, spindle_on,  # type: ignore[arg-type]
                    None if velocity is None else tuple(velocity), flags,  # type: ignore[arg-type]
                    self.stream)
        self.counters["sent"] += 1
        return seq, encode_pose(pose, self.tagger)

    def _handshake(self, notice: Notice) -> None:
        """Follow a verified NEW_STREAM or WRONG_STREAM notice."""
        if notice.error == NEW_STREAM:
            if (self.stream == HELLO_STREAM and notice.stream != HELLO_STREAM
                    and self._hellos.get(notice.seq) == notice.t_client_us):
                self.stream = notice.stream
                self._hellos.clear()
                self.counters["streams"] += 1
        elif notice.stream == self.stream != HELLO_STREAM:
            self.stream = HELLO_STREAM
            self._hellos.clear()  # answers to hellos before this stream are not for this round
            self.counters["wrong_stream"] += 1

    def accept(self, data: bytes, arrived_us: int) -> Result | Notice | None:
        """The datagram (arrived at ``arrived_us``) as a Result or Notice, or None if it is
        not to be believed."""
        try:
            message = decode_server_message(data)
        except ProtocolError:
            self.counters["malformed"] += 1
            return None
        handshake = isinstance(message, Notice) and message.error in HANDSHAKE_NOTICES
        if self.tagger is not None and (isinstance(message, Reply) or handshake) and (
                message.tag is None or not self.tagger.verify(data)):
            # Replies and handshake notices of a keyed session are always tagged: anything
            # else is forged or corrupt (a forged WRONG_STREAM would end the stream). Other
            # notices are passed on unverified: they carry no force and change nothing, and
            # one that says BAD_TAG is tagged with the server's key, which a client with the
            # wrong key cannot check — yet it must learn that its key is wrong.
            self.counters["bad_tag"] += 1
            return None
        if message.session != self.session:
            self.counters["foreign"] += 1
            return None
        self.counters["received"] += 1
        if isinstance(message, Notice):
            self.counters["notices"] += 1
            if handshake:
                self._handshake(message)
            return message
        if self.newest is not None and not seq_after(message.seq, self.newest):
            self.counters["stale"] += 1
            return None
        self.newest = message.seq
        offset = ((message.t_recv_us - message.t_client_us)
                  + (message.t_send_us - arrived_us)) / 2.0
        return Result(message, float(arrived_us - message.t_client_us), offset)

    @staticmethod
    def answer_to(item: Result | Notice, seq: int) -> Result | Notice | None:
        """``item`` if it answers packet ``seq`` (None if it answers another): a Result, or a
        NEW_STREAM / WRONG_STREAM notice (the pose was not ticked: send it again, it now goes
        out in the new stream or as a hello).

        Raises:
            ServerError: it answers ``seq`` with another notice or an error reply.
        """
        if isinstance(item, Notice):
            if item.seq != seq:
                return None
            if item.error in HANDSHAKE_NOTICES:
                return item
            raise ServerError(item.error, seq)
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
        first_seq: the first sequence number (any: the server starts a stream's sequence at
            the stream's first POSE).
        give_way: when another client takes the session's stream, stop (:meth:`send` and
            :meth:`exchange` raise :class:`StreamTaken`) instead of taking it back.

    Replies are checked as ``SessionRules`` says; ``counters`` counts what was sent,
    received and dropped. :meth:`send`, :meth:`receive` and :meth:`exchange` raise
    :class:`ServerGone` when nothing listens on the server's port any more.
    """

    def __init__(self, host: str, port: int, session: int = 1, key: bytes | str | None = None,
                 timeout_s: float = 0.1, first_seq: int = 1, give_way: bool = False) -> None:
        self.rules = SessionRules(session, key, first_seq, give_way)
        self.counters = self.rules.counters
        self.timeout_s = timeout_s
        self.host = host
        self.port = port
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

        Raises:
            ServerGone: an earlier datagram found nothing listening on the server's port.
            StreamTaken: ``give_way``, and another client took the session's stream.
        """
        seq, datagram = self.rules.datagram(position, orientation, rpm, spindle_on, velocity,
                                            flags, t_us)
        try:
            self.sock.send(datagram)
        except ConnectionRefusedError:  # the ICMP answer to an earlier datagram
            raise ServerGone(self.host, self.port) from None
        return seq

    def receive(self, timeout_s: float | None = None) -> Result | Notice | None:
        """The next verified reply or notice, or None if none arrives within the timeout
        (0: only what has already arrived).

        Raises:
            ServerGone: nothing listens on the server's port (reported once per ICMP error:
                a later call waits again).
        """
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            remaining = deadline - time.monotonic()
            self.sock.settimeout(max(remaining, 0.0))
            try:
                data = self.sock.recv(MAX_REPLY_BYTES + 1)
            except (BlockingIOError, TimeoutError):
                return None
            except ConnectionRefusedError:  # ICMP: nothing listens on the server's port
                raise ServerGone(self.host, self.port) from None
            message = self.rules.accept(data, now_us())
            if message is not None:
                return message

    def exchange(self, position: Sequence[float], orientation: Sequence[float] = IDENTITY,
                 rpm: float = 0.0, spindle_on: bool = True,
                 velocity: Sequence[float] | None = None, flags: int = 0,
                 timeout_s: float | None = None) -> Result:
        """Send a pose and wait for its reply. Without a stream the pose goes out as a hello:
        then, once the server has given one, the same pose again in it, and its reply is
        returned (likewise after the server ended the stream). ``timeout_s`` is per send.

        Raises:
            TimeoutError: no reply within the timeout.
            ServerError: the server answered with a notice or an error reply.
            ServerGone: nothing listens on the server's port.
        """
        wait = self.timeout_s if timeout_s is None else timeout_s
        for _ in range(MAX_RESENDS + 1):
            seq = self.send(position, orientation, rpm, spindle_on, velocity, flags)
            deadline = time.monotonic() + wait
            while True:
                message = self.receive(max(deadline - time.monotonic(), 0.0))
                if message is None:
                    self.counters["timeouts"] += 1
                    raise TimeoutError(f"no reply to packet {seq} within {wait:g} s")
                result = SessionRules.answer_to(message, seq)
                if result is not None:
                    break
            if isinstance(result, Result):
                return result
        raise ServerError(result.error, seq)
