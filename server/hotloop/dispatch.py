"""From a datagram to the bytes of its answer: decode, authenticate, order, tick, encode.

:meth:`Dispatcher.handle` never raises: every datagram is answered, noticed or dropped, and
counted under one reason. No sockets here (the loop owns them), so it is testable directly.
"""

from __future__ import annotations

import logging
import time
from contextlib import AbstractContextManager, nullcontext

import numpy as np

from ...proto.codec import (
    ProtocolError,
    decode_pose,
    encode_bad_version_v1,
    encode_notice_values,
    encode_pose,
)
from ...proto.messages import (
    BAD_TAG,
    BAD_VERSION,
    ERROR_NAMES,
    INTERNAL,
    NEW_STREAM,
    OK,
    TAG_BYTES,
    UNKNOWN_SESSION,
    VERSION_1,
    WRONG_STREAM,
    Pose,
)
from .. import compile_cache
from . import wire
from .bucket import TokenBucket
from .session import Session
from .wire import RX_BYTES, decode_pose_into, new_buffers, pose_arrays

log = logging.getLogger("burrforce.hotloop")

#: Notices (answers to datagrams that could not be used) per second, and the burst allowed:
#: enough for a developer to see what is wrong, too few to make the server a flood's echo.
NOTICE_RATE_HZ = 200.0
NOTICE_BURST = 50.0
#: INTERNAL errors logged with a traceback at most this often, s.
INTERNAL_LOG_INTERVAL_S = 1.0


class Dispatcher:
    """The sessions of one hot loop and the protocol in front of them.

    Counters (``counters``): ``received``, ``replied``, ``noticed``, ``notices_suppressed``,
    ``send_errors``, and one per error name (``malformed``, ``too_big``, ``bad_version``,
    ``bad_type``, ``unknown_session``, ``bad_tag``, ``bad_value``, ``stale``, ``duplicate``,
    ``internal``, ``wrong_stream``) for datagrams that were not processed normally;
    ``new_stream`` counts hellos (answered or not); ``restoring`` datagrams held for a
    session being restored (``restoring``).

    Processing order (SPEC.md 3.4): size, decode, session, tag, stream, sequence, values.
    """

    def __init__(self) -> None:
        self.sessions: dict[int, Session] = {}
        self.counters: dict[str, int] = {"received": 0, "replied": 0, "noticed": 0,
                                         "notices_suppressed": 0, "send_errors": 0,
                                         "restoring": 0}
        for code, name in ERROR_NAMES.items():
            if code != OK:
                self.counters[name] = 0
        #: The last datagram :meth:`handle` took was a POSE a session accepted (authentic, in
        #: its open stream, newer than the last): the loop gives its sender a socket of its own.
        self.accepted = False
        #: Ids of sessions being put back after a restart (``HotLoopConfig.restoring``):
        #: their datagrams go unanswered until :meth:`add` brings each back.
        self.restoring: set[int] = set()
        self._notices = TokenBucket(NOTICE_RATE_HZ, NOTICE_BURST)
        self._internal_logged_ns = -(1 << 62)
        #: The datagram buffer (the loop receives into ``rx_view``), the decoded pose, and
        #: the reply buffer: one set for the loop's thread, reused by every packet.
        self.rx, self._pose_i, self._pose_f, self.tx, _ = new_buffers()
        self.rx_view = memoryview(self.rx)
        self.tx_view = memoryview(self.tx)

    def add(self, session: Session) -> None:
        if session.id in self.sessions:
            raise ValueError(f"session {session.id} exists")
        self.sessions[session.id] = session
        self.restoring.discard(session.id)

    def warm_up(self, ticks: bool = True) -> None:
        """Run a hello, a commit, a tick and an unusable pose per session through decode,
        tag, tick and encode (a pose far outside the bone: nothing is carved), so no first
        packet pays for compiling or importing (the general decoder's path too: the hello is
        sent in a non-canonical form); then forget them and start counting from zero (the stream
        the warm-up used is ended; ``next_stream`` is as it was).

        ``ticks`` False: not the sessions' bone ticks (``BoneEngine.warm_up``), for a compile
        job that leaves them to another process (its sessions have the model off)."""
        wire.warm_up()
        # Every burr's tick, the other shapes' too, so that a tool change mid-stream need
        # not load kernels — once ``burrforce compile`` has filled the cache. Until then
        # (a first start) only the sessions' own burrs: the rest would take the first
        # session as long again to compile; a tool change waits for them instead
        # (``commands``), off the packet path.
        every_burr = compile_cache.is_complete()
        for session in self.sessions.values():
            if ticks:
                session.engine.warm_up(every_burr)
            first = session.next_stream
            far = session.transform.point_out((-1e5, -1e5, -1e5))
            pose = Pose(session.id, 0, 1, far, (0.0, 0.0, 0.0, 1.0),
                        session.engine.params.min_cutting_rpm + 1.0, True)
            hello = encode_pose(pose, session.tagger)
            # The hello with its version as a uint 8 (cc 02): valid, not canonical.
            hello = hello[:1] + b"\xcc" + hello[1:]
            if session.tagger is not None:
                hello = hello[:-TAG_BYTES] + session.tagger.mac(hello[:-TAG_BYTES])
            self.handle(hello, time.monotonic_ns())
            stream = session.offer
            # The commit, a tick of the open stream, and a BAD_VALUE reply.
            for seq, rpm in ((1, pose.rpm), (2, pose.rpm), (3, float("nan"))):
                self.handle(encode_pose(pose._replace(seq=seq, t_client_us=1 + seq,
                                                      stream=stream, rpm=rpm),
                                        session.tagger), time.monotonic_ns())
            session.reset_statistics()
            # The warm-up's stream never left this process: the first number a client gets
            # is still the one the session was given.
            session.next_stream = first
        for name in self.counters:
            self.counters[name] = 0

    def handle(self, data: bytes, t_recv_ns: int, peer: object = None) -> bytes | None:
        """The answer to ``data`` (received at ``t_recv_ns``, monotonic, from ``peer``), or
        None."""
        n = len(data)
        if n <= RX_BYTES:
            self.rx_view[:n] = data
        out = self.handle_received(n, t_recv_ns, data, peer)
        return bytes(out) if type(out) is memoryview else out

    def handle_received(self, n: int, t_recv_ns: int, data: bytes | None = None,
                        peer: object = None) -> memoryview | bytes | None:
        """The answer to the ``n`` bytes in ``rx`` (received at ``t_recv_ns``), or None. The
        answer may be a slice of the reply buffer: send it before the next datagram.

        ``data``: the datagram as bytes if the caller has it (else it is copied out of ``rx``
        for the general decoder when it is not a canonical POSE); required if ``n`` >
        RX_BYTES. ``peer``: the sender's address. A stream is offered to one address and
        ticked only for the address that opened it (SPEC.md 5.2): the same number never
        serves two clients."""
        counters = self.counters
        counters["received"] += 1
        self.accepted = False
        pose_i = self._pose_i
        try:
            if not decode_pose_into(self.rx, n, pose_i, self._pose_f):
                # Not the canonical layout: the general decoder, which knows every other
                # valid form and what is wrong with the rest.
                if data is None:
                    data = bytes(self.rx_view[:n])
                pose_arrays(decode_pose(data), pose_i, self._pose_f)
        except ProtocolError as exc:
            return self._reject(exc.code, exc.header, n, None, t_recv_ns, exc.version)
        except Exception:  # a decoder bug must not stop the loop
            return self._internal(None, t_recv_ns)
        sid, seq, t_client, _, stream, _, _, has_tag = pose_i.tolist()
        session = self.sessions.get(sid)
        if session is None:
            if sid in self.restoring:  # back in a moment: held, as if lost on the way
                counters["restoring"] += 1
                return None
            return self._reject(UNKNOWN_SESSION, (sid, seq, t_client), n, None, t_recv_ns)
        tagger = session.tagger
        if tagger is not None and (not has_tag or not tagger.verify(
                self.rx_view[:n] if data is None else data)):
            return self._reject(BAD_TAG, (sid, seq, t_client), n, session, t_recv_ns)
        # 0 is never an open stream; a stream's POSE from another address is another
        # client's (or a replay from elsewhere): refused, so that client hears it.
        if stream == 0 or stream != session.stream or peer != session.stream_peer:
            if not session.offered(stream, peer):
                return self._handshake(session, seq, t_client, stream, n, t_recv_ns, peer)
            session.commit(peer)
        order = session.admit(seq)
        if order != OK:  # stale and duplicate datagrams are never answered (replays)
            counters[ERROR_NAMES[order]] += 1
            return None
        self.accepted = True
        try:
            out, error = session.respond_into(pose_i, self._pose_f, t_recv_ns, self.tx,
                                              self.tx_view)
        except Exception:
            session.counters["internal"] += 1
            return self._internal(session, t_recv_ns)
        if error != OK:
            counters[ERROR_NAMES[error]] += 1
        counters["replied"] += 1
        return out

    def _handshake(self, session: Session, seq: int, t_client_us: int, stream: int, size: int,
                   now_ns: int, peer: object) -> bytes | None:
        """A hello (answered NEW_STREAM with ``peer``'s offer) or a POSE of a stream that is
        not open for ``peer`` (WRONG_STREAM): never ticked, answered within the session's own
        notice bucket and never longer than the request."""
        counters = self.counters
        hello = stream == 0
        code = NEW_STREAM if hello else WRONG_STREAM
        session.counters["hellos" if hello else "wrong_stream"] += 1
        counters[ERROR_NAMES[code]] += 1
        if not session.stream_notice_allowed(now_ns, not hello):
            counters["notices_suppressed"] += 1
            return None
        if hello:  # after the bucket: hellos beyond its rate use up no numbers
            stream = session.hello(peer)
        notice = encode_notice_values(session.id, seq, t_client_us, code, stream,
                                      session.tagger)
        if len(notice) > size:
            return None
        counters["noticed"] += 1
        return notice

    def _reject(self, code: int, header: tuple[int, int, int] | None, size: int,
                session: Session | None, now_ns: int,
                version: int | None = None) -> bytes | None:
        """Count a rejected datagram; a short notice when it is addressable and no longer than
        the datagram itself (so answering never amplifies), within the notice rate."""
        self.counters[ERROR_NAMES[code]] += 1
        if header is None:
            return None
        # The rate first: under a flood, suppressed notices are never encoded or signed.
        if self._notices.refill(now_ns) < 1.0:
            self.counters["notices_suppressed"] += 1
            return None
        if code == BAD_VERSION and version == VERSION_1:  # in v1's shape: "update me"
            notice = encode_bad_version_v1(*header)
        else:
            notice = encode_notice_values(*header, code, 0,
                                          session.tagger if session is not None else None)
        if len(notice) > size:
            return None
        self._notices.tokens -= 1.0  # taken only for a notice that is sent
        self.counters["noticed"] += 1
        return notice

    def _internal(self, session: Session | None, now_ns: int) -> memoryview | None:
        """Count (and log, at most once a second) a failure; for a session's admitted pose
        (in ``_pose_i``), an INTERNAL reply."""
        self.counters["internal"] += 1
        if now_ns - self._internal_logged_ns > INTERNAL_LOG_INTERVAL_S * 1e9:
            self._internal_logged_ns = now_ns
            log.exception("internal error on a datagram (further ones within %.0f s are only "
                          "counted)", INTERNAL_LOG_INTERVAL_S)
        if session is None:
            return None
        try:  # zero force with the error, so the client does not keep rendering the last one
            return session.error_reply(self._pose_i, INTERNAL, now_ns, self.tx, self.tx_view)
        except Exception:
            return None

    def snapshot(self, lock: AbstractContextManager | None = None,
                 tick_times_since: dict[int, tuple[int, int]] | None = None
                 ) -> dict[str, object]:
        """Counters and per-session statistics (plain data, picklable). Only the copying
        holds ``lock`` (the loop's): the quantiles are computed after it is released.

        With ``tick_times_since`` (session id → a previous (``tick_epoch``, ``ticks_timed``)),
        each session also carries ``new_tick_times_us``: the model-stage times of the ticks
        since then that are still kept, or of all kept ticks for a session (or an epoch) the
        caller has not seen (a metrics poller builds its histogram from them)."""
        with lock if lock is not None else nullcontext():
            counters = dict(self.counters)
            sessions = {sid: s.stats() for sid, s in self.sessions.items()}
        for sid, stats in sessions.items():
            times = stats.pop("tick_times_us")
            if tick_times_since is not None:
                epoch, seen = tick_times_since.get(sid, (0, 0))
                new = stats["ticks_timed"] - (seen if epoch == stats["tick_epoch"] else 0)
                stats["new_tick_times_us"] = (times[-new:] if 0 < new <= len(times)
                                              else times if new > 0 else times[:0])
            stats["tick_p50_us"] = float(np.median(times)) if len(times) else None
            stats["tick_p99_us"] = float(np.percentile(times, 99)) if len(times) else None
        return {"counters": counters, "time_ns": time.monotonic_ns(), "sessions": sessions}
