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
    UNKNOWN_SESSION,
    VERSION_1,
    WRONG_STREAM,
    Pose,
)
from .bucket import TokenBucket
from .session import Session

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
    ``new_stream`` counts hellos (answered or not).

    Processing order (SPEC.md 3.4): size, decode, session, tag, stream, sequence, values.
    """

    def __init__(self) -> None:
        self.sessions: dict[int, Session] = {}
        self.counters: dict[str, int] = {"received": 0, "replied": 0, "noticed": 0,
                                         "notices_suppressed": 0, "send_errors": 0}
        for code, name in ERROR_NAMES.items():
            if code != OK:
                self.counters[name] = 0
        #: The last datagram :meth:`handle` took was a POSE a session accepted (authentic, in
        #: its open stream, newer than the last): the loop gives its sender a socket of its own.
        self.accepted = False
        self._notices = TokenBucket(NOTICE_RATE_HZ, NOTICE_BURST)
        self._internal_logged_ns = -(1 << 62)

    def add(self, session: Session) -> None:
        if session.id in self.sessions:
            raise ValueError(f"session {session.id} exists")
        self.sessions[session.id] = session

    def warm_up(self) -> None:
        """Run a hello, a commit and a tick per session through decode, tag, tick and encode
        (a pose far outside the bone: nothing is carved), so no first packet pays for
        compiling or importing; then forget them and start counting from zero (the stream
        the warm-up used is ended; ``next_stream`` is as it was)."""
        for session in self.sessions.values():
            first = session.next_stream
            far = session.transform.point_out((-1e5, -1e5, -1e5))
            pose = Pose(session.id, 0, 1, far, (0.0, 0.0, 0.0, 1.0),
                        session.engine.params.min_cutting_rpm + 1.0, True)
            self.handle(encode_pose(pose, session.tagger), time.monotonic_ns())  # hello
            stream = session.offer
            for seq in (1, 2):  # the commit, then a tick of the open stream
                self.handle(encode_pose(pose._replace(seq=seq, t_client_us=1 + seq,
                                                      stream=stream), session.tagger),
                            time.monotonic_ns())
            session.reset_statistics()
            # The warm-up's stream never left this process: the first number a client gets
            # is still the one the session was given.
            session.next_stream = first
        for name in self.counters:
            self.counters[name] = 0

    def handle(self, data: bytes, t_recv_ns: int) -> bytes | None:
        """The answer to ``data`` (received at ``t_recv_ns``, monotonic), or None."""
        counters = self.counters
        counters["received"] += 1
        self.accepted = False
        try:
            pose = decode_pose(data)
        except ProtocolError as exc:
            return self._reject(exc.code, exc.header, len(data), None, t_recv_ns,
                                exc.version)
        except Exception:  # a decoder bug must not stop the loop
            return self._internal(None, t_recv_ns)
        header = (pose.session, pose.seq, pose.t_client_us)
        session = self.sessions.get(pose.session)
        if session is None:
            return self._reject(UNKNOWN_SESSION, header, len(data), None, t_recv_ns)
        tagger = session.tagger
        if tagger is not None and (pose.tag is None or not tagger.verify(data)):
            return self._reject(BAD_TAG, header, len(data), session, t_recv_ns)
        stream = pose.stream
        if stream == 0 or stream != session.stream:  # 0 is never an open stream
            if stream == 0 or stream != session.offer:
                return self._handshake(session, pose, len(data), t_recv_ns)
            session.commit()
        order = session.admit(pose.seq)
        if order != OK:  # stale and duplicate datagrams are never answered (replays)
            counters[ERROR_NAMES[order]] += 1
            return None
        self.accepted = True
        try:
            out, error = session.respond(pose, t_recv_ns)
        except Exception:
            session.counters["internal"] += 1
            return self._internal(session, t_recv_ns, pose)
        if error != OK:
            counters[ERROR_NAMES[error]] += 1
        counters["replied"] += 1
        return out

    def _handshake(self, session: Session, pose: Pose, size: int, now_ns: int) -> bytes | None:
        """A hello (answered NEW_STREAM with the offer) or a POSE of a stream that is not
        open (WRONG_STREAM): never ticked, answered within the session's own notice bucket
        and never longer than the request."""
        counters = self.counters
        if pose.stream == 0:
            code, stream = NEW_STREAM, session.hello()
        else:
            code, stream = WRONG_STREAM, pose.stream
            session.counters["wrong_stream"] += 1
        counters[ERROR_NAMES[code]] += 1
        if not session.stream_notice_allowed(now_ns, code == WRONG_STREAM):
            counters["notices_suppressed"] += 1
            return None
        notice = encode_notice_values(session.id, pose.seq, pose.t_client_us, code, stream,
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

    def _internal(self, session: Session | None, now_ns: int,
                  pose: Pose | None = None) -> bytes | None:
        self.counters["internal"] += 1
        if now_ns - self._internal_logged_ns > INTERNAL_LOG_INTERVAL_S * 1e9:
            self._internal_logged_ns = now_ns
            log.exception("internal error on a datagram (further ones within %.0f s are only "
                          "counted)", INTERNAL_LOG_INTERVAL_S)
        if session is None or pose is None:
            return None
        try:  # zero force with the error, so the client does not keep rendering the last one
            return session.error_reply(pose, INTERNAL, now_ns)
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
