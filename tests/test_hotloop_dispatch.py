"""The protocol in front of the sessions, without sockets: Dispatcher.handle on real engines."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.proto import frames
from burrforce.proto.codec import (
    ProtocolError,
    decode_pose,
    decode_server_message,
    encode_notice,
    encode_pose,
)
from burrforce.proto.messages import (
    BAD_TAG,
    BAD_VALUE,
    BAD_VERSION,
    FLAG_RESET_VELOCITY,
    INTERNAL,
    NEW_STREAM,
    NOTICE_FIELDS,
    OK,
    STATUS_CONTACT,
    STATUS_CUTTING,
    STATUS_SLOW_SPINDLE,
    STATUS_STALE,
    UNKNOWN_SESSION,
    WRONG_STREAM,
    Notice,
    Pose,
    Reply,
)
from burrforce.proto.tag import Tagger
from burrforce.server.bone import BoneEngine, workpiece_block
from burrforce.server.hotloop import Dispatcher, Session, SessionConfig
from burrforce.server.hotloop.dispatch import NOTICE_BURST
from burrforce.server.hotloop.session import MAX_OFFERS, STREAM_NOTICE_BURST
from burrforce.server.model import CuttingModel, CuttingParams
from burrforce.server.model.cases import CuttingCase

IDENTITY = (0.0, 0.0, 0.0, 1.0)

KEY = bytes(range(32))
TAGGER = Tagger(KEY)
T0_NS = 10**12
ALPHA_DEG = 60.0
#: The stream make()'s sessions have open (their first offer).
STREAM = 0xC0FFEE


def tilted(alpha_deg: float = ALPHA_DEG) -> tuple[float, float, float, float]:
    """Quaternion taking +z to the thesis's tool axis (−cos α, 0, sin α)."""
    beta = math.radians(alpha_deg - 90.0)
    return (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))


def make(voxel_mm: float = 0.25, frame: str = "si_mm", key: bytes | None = KEY,
         open_stream: bool = True, **config) -> tuple[Dispatcher, Session]:
    """A dispatcher with session 1; with ``open_stream`` its stream STREAM is open (the
    handshake done through the session's own calls, nothing ticked)."""
    grid = workpiece_block(voxel_mm)
    session = Session(1, BoneEngine(grid), SessionConfig(frame=frame, **config), key,
                      next_stream=STREAM)
    if open_stream:
        assert session.hello() == STREAM
        session.commit()
    d = Dispatcher()
    d.add(session)
    return d, session


def send(d: Dispatcher, seq: int, position, *, t_us: int | None = None, key=KEY,
         orientation=(0.0, 0.0, 0.0, 1.0), rpm=60_000.0, on=True, velocity=None, flags=0,
         now_ns: int | None = None, session: int = 1, stream: int = STREAM, peer=None):
    t_us = seq * 1000 if t_us is None else t_us
    pose = Pose(session, seq, t_us, tuple(position), tuple(orientation), rpm, on, velocity,
                flags, stream)
    data = encode_pose(pose, Tagger(key) if key is not None else None)
    out = d.handle(data, T0_NS + t_us * 1000 if now_ns is None else now_ns, peer)
    return None if out is None else decode_server_message(out)


def groove(d: Dispatcher, n: int, frame: frames.Frame, depth_mm=0.5, feed_mm_s=3.0,
           x0=2.0) -> list[Reply]:
    """The thesis's parallel cut at α = 60°, n ticks at 1 kHz, sent in ``frame``."""
    tf = frames.Transform(frame)
    axis_server = (-math.cos(math.radians(ALPHA_DEG)), 0.0, math.sin(math.radians(ALPHA_DEG)))
    from burrforce.client.demo import shortest_arc

    q = shortest_arc(frame.tool_axis, tf.direction_out(axis_server))
    replies = []
    for k in range(1, n + 1):
        p = tf.point_out((x0 + feed_mm_s * k * 1e-3, 0.0, 2.0 - depth_mm))
        replies.append(send(d, k, p, orientation=q))
    return replies


# -- physics through the protocol -------------------------------------------------------------
def test_steady_groove_through_the_protocol_matches_the_model():
    d, _ = make(voxel_mm=0.1)
    replies = groove(d, 1500, frames.frame("si_mm"))
    steady = np.array([r.resistive for r in replies[700:]])
    assert all(r.error == OK for r in replies)
    assert all(r.status & STATUS_CUTTING for r in replies[700:])
    case = CuttingCase("parallel", ALPHA_DEG)
    want = CuttingModel(CuttingParams()).evaluate(case.centre_mm, case.axis,
                                                  case.feed_velocity_mm_s, case.rpm)
    got = steady.mean(axis=0)
    assert got[0] == pytest.approx(want.feed_N, rel=0.02)
    assert got[2] == pytest.approx(want.normal_N, rel=0.02)
    assert abs(got[1] - want.lateral_N) < 0.02 * abs(want.normal_N)
    # The energy balance holds through the protocol: P = Us × removal rate, tick by tick.
    power = np.array([r.power_w for r in replies[700:]])
    removed = np.array([r.removed_mm3 for r in replies[700:]])
    assert power.mean() == pytest.approx(805.1 * removed.mean() / 1e-3 * 1e-3, rel=0.02)


@pytest.mark.parametrize("name", ["unity", "unreal", "godot", "ros"])
def test_every_engine_frame_feels_the_same_cut(name):
    """The same physical groove sent in another engine's frame gives the same force, torque
    and velocity, converted: the edge conversion is exact both ways."""
    ref_d, _ = make()
    other_d, _ = make(frame=name)
    frame = frames.frame(name)
    tf = frames.Transform(frame)
    ref = groove(ref_d, 300, frames.frame("si_mm"))
    got = groove(other_d, 300, frame)
    assert any(r.status & STATUS_CUTTING for r in ref)
    for a, b in zip(ref, got, strict=True):
        assert b.status == a.status
        np.testing.assert_allclose(tf.direction_in(b.force), a.force, atol=1e-9)
        np.testing.assert_allclose(b.resistive, a.resistive, atol=1e-9)
        # Torque: N·L back to N·mm with the handedness sign (a pseudovector).
        t = np.array(tf.direction_in(b.torque)) * tf.scale * tf.det
        np.testing.assert_allclose(t, a.torque, atol=1e-7)
        np.testing.assert_allclose(tf.vector_in(b.feed_velocity), a.feed_velocity,
                                   atol=1e-6)
        assert b.removed_mm3 == pytest.approx(a.removed_mm3, abs=1e-12)


def test_spindle_off_touches_and_cuts_nothing():
    d, s = make()
    replies = [send(d, k, (5.0 + 0.003 * k, 0.0, 1.5), on=False) for k in range(1, 50)]
    assert all(r.removed_mm3 == 0.0 for r in replies)
    assert replies[-1].status & STATUS_CONTACT
    assert not replies[-1].status & STATUS_CUTTING
    assert replies[-1].vibration_amplitude == 0.0 and replies[-1].vibration_frequency_hz == 0.0
    slow = send(d, 60, (5.2, 0.0, 1.5), rpm=1000.0)
    assert slow.status & STATUS_SLOW_SPINDLE and slow.removed_mm3 == 0.0
    assert s.engine.grid.version == 0


def test_vibration_parameters_follow_the_spindle():
    d, _ = make()
    r = send(d, 1, (5.0, 0.0, 30.0), rpm=-45_000.0)
    assert r.vibration_frequency_hz == pytest.approx(750.0)
    assert r.vibration_amplitude == pytest.approx(0.5)  # Fd default, burring gain 0
    assert np.linalg.norm(r.vibration_axis) == pytest.approx(1.0)


def test_model_off_answers_with_zero_force():
    d, s = make(model=False)
    r = send(d, 1, (5.0, 0.0, 1.5))
    assert r.error == OK and r.force == (0.0, 0.0, 0.0) and r.removed_mm3 == 0.0
    assert s.ticks_timed == 0


# -- sequence numbers and streams --------------------------------------------------------------
def test_stale_and_duplicate_are_dropped_silently_and_counted():
    d, s = make()
    assert send(d, 10, (5.0, 0.0, 30.0)) is not None
    assert send(d, 10, (5.0, 0.0, 30.0), t_us=10_001) is None  # duplicate
    assert send(d, 9, (5.0, 0.0, 30.0), t_us=10_002) is None  # stale
    assert send(d, 11, (5.0, 0.0, 30.0)) is not None
    assert d.counters["duplicate"] == 1 and d.counters["stale"] == 1
    assert s.counters["duplicate"] == 1 and s.counters["stale"] == 1


def test_sequence_numbers_wrap_around():
    d, _ = make()
    top = (1 << 32) - 1
    assert send(d, top - 1, (5.0, 0.0, 30.0), t_us=1000) is not None
    assert send(d, top, (5.0, 0.0, 30.0), t_us=2000) is not None
    assert send(d, 0, (5.0, 0.0, 30.0), t_us=3000) is not None
    assert send(d, 1, (5.0, 0.0, 30.0), t_us=4000) is not None
    assert send(d, top, (5.0, 0.0, 30.0), t_us=5000) is None  # now stale
    assert d.counters["stale"] == 1


def test_hello_is_answered_with_the_offer_and_never_ticked():
    d, s = make(open_stream=False)
    for seq in (1, 2, 3):  # idempotent: the same offer until it is used
        n = send(d, seq, (5.0, 0.0, 1.5), stream=0)
        assert isinstance(n, Notice) and (n.error, n.stream, n.seq) == (NEW_STREAM, STREAM, seq)
        assert n.tag is not None and encode_notice_of(n)[-16:] == n.tag
    assert s.counters["accepted"] == 0 and s.engine.grid.version == 0 and s.last_seq is None
    assert (s.stream, s.offer, s.counters["hellos"]) == (0, STREAM, 3)
    # The first POSE of the offered stream commits it: any seq, a normal reply, STALE.
    r = send(d, 2, (5.0, 0.0, 1.5), stream=STREAM)
    assert isinstance(r, Reply) and r.status & STATUS_STALE
    assert (s.stream, s.offer, s.counters["streams"]) == (STREAM, 0, 1)
    assert isinstance(send(d, 3, (5.003, 0.0, 1.5)), Reply)
    assert send(d, 3, (5.003, 0.0, 1.5)) is None  # v1 sequencing within the stream
    assert d.counters["new_stream"] == 3 and d.counters["replied"] == 2


def encode_notice_of(n: Notice) -> bytes:
    """``n`` encoded again with the test key: verifies if and only if ``n.tag`` is right."""
    return encode_notice(n, TAGGER)


def test_a_hello_never_disturbs_the_open_stream_and_numbers_are_never_reused():
    d, s = make()
    assert send(d, 10, (5.0, 0.0, 30.0)) is not None
    n = send(d, 11, (5.0, 0.0, 30.0), stream=0)  # a replayed hello, say
    assert (n.error, n.stream) == (NEW_STREAM, STREAM + 1)
    assert isinstance(send(d, 12, (5.0, 0.0, 30.0)), Reply)  # the stream goes on
    assert s.stream == STREAM and s.last_seq == 12
    # The client's own restart: hello, commit the new offer; the old stream is over.
    assert isinstance(send(d, 1, (5.0, 0.0, 30.0), stream=STREAM + 1), Reply)
    n = send(d, 13, (5.0, 0.0, 30.0), stream=STREAM)
    assert (n.error, n.stream) == (WRONG_STREAM, STREAM) and encode_notice_of(n)[-16:] == n.tag
    assert send(d, 0, (5.0, 0.0, 30.0), stream=0).stream == STREAM + 2
    assert s.counters["wrong_stream"] == 1 and d.counters["wrong_stream"] == 1


def test_end_stream_makes_the_client_say_hello_again():
    d, s = make()
    captured = [encode_pose(Pose(1, k, k * 1000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0),
                                 60_000.0, True, None, 0, STREAM), TAGGER) for k in (1, 2)]
    assert all(isinstance(decode_server_message(d.handle(c, T0_NS)), Reply) for c in captured)
    s.end_stream()
    assert (s.stream, s.offer) == (0, 0)
    for c in captured:
        n = decode_server_message(d.handle(c, T0_NS + 2 * 10**9))
        assert (n.error, n.stream) == (WRONG_STREAM, STREAM)
    assert send(d, 3, (5.0, 0.0, 1.5), stream=0).stream == STREAM + 1
    assert isinstance(send(d, 4, (5.0, 0.0, 1.5), stream=STREAM + 1), Reply)
    assert s.counters["accepted"] == 3


def test_replays_after_idle_are_never_answered():
    """v1 restarted an idle stream (replays accepted); v2 streams never reopen by themselves."""
    d, s = make()
    captured = [encode_pose(Pose(1, k, k * 1000, (5.0 + 0.003 * k, 0.0, 1.5),
                                 (0.0, 0.0, 0.0, 1.0), 60_000.0, True, None, 0, STREAM),
                            TAGGER) for k in range(1, 30)]
    for c in captured:
        assert d.handle(c, T0_NS) is not None
    version = s.engine.grid.version
    for c in captured:
        assert d.handle(c, T0_NS + 5 * 10**9) is None  # 5 s later
    assert s.engine.grid.version == version and s.counters["accepted"] == len(captured)


def test_stream_notices_have_a_bucket_per_session():
    d, s = make(open_stream=False)
    # A flood of junk empties the server-wide bucket; the handshake still gets through.
    junk = encode_pose(Pose(77, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False))
    while d.handle(junk, T0_NS) is not None:
        pass
    assert send(d, 1, (5.0, 0.0, 1.5), stream=0, now_ns=T0_NS).error == NEW_STREAM
    answered = 1 + sum(send(d, 2, (5.0, 0.0, 1.5), stream=0, now_ns=T0_NS) is not None
                       for _ in range(100))
    assert answered == STREAM_NOTICE_BURST
    # 10 ms later the bucket holds one token again (100/s).
    assert send(d, 3, (5.0, 0.0, 1.5), stream=0, now_ns=T0_NS + 10**7) is not None
    assert s.counters["hellos"] == 102 and s.offer == STREAM


def test_two_clients_saying_hello_at_once_get_streams_of_their_own():
    """The issue's collision (SPEC 5.2): two clients (two source addresses) say hello before
    either uses its number. Each is offered a number of its own, only its own address may
    open it, and a client whose stream is taken, or who uses one not its own, hears
    WRONG_STREAM: never silence, whatever its sequence numbers."""
    d, s = make(open_stream=False)
    a, b = ("10.0.0.1", 40000), ("10.0.0.2", 40000)
    up = (5.0, 0.0, 30.0)
    na = send(d, 100, up, stream=0, peer=a)
    nb = send(d, 1, up, stream=0, peer=b)
    assert (na.error, nb.error) == (NEW_STREAM, NEW_STREAM) and na.stream != nb.stream
    assert send(d, 101, up, stream=0, peer=a).stream == na.stream  # idempotent per source
    n = send(d, 2, up, stream=na.stream, peer=b)  # A's number from B's address
    assert (n.error, n.stream) == (WRONG_STREAM, na.stream) and s.stream == 0
    assert isinstance(send(d, 102, up, stream=na.stream, peer=a), Reply)
    assert (s.stream, s.stream_peer, s.offers) == (na.stream, a, {})
    # A's commit withdrew B's offer: B hears so, asks again and takes the stream.
    n = send(d, 3, up, stream=nb.stream, peer=b)
    assert (n.error, n.stream) == (WRONG_STREAM, nb.stream)
    nb2 = send(d, 4, up, stream=0, peer=b)
    assert nb2.stream not in (na.stream, nb.stream)
    assert isinstance(send(d, 5, up, stream=nb2.stream, peer=b), Reply)
    n = send(d, 103, up, stream=na.stream, peer=a)
    assert (n.error, n.stream) == (WRONG_STREAM, na.stream)
    # B's open stream used from A's address (a number A adopted wrongly, or a replay from
    # elsewhere), with a seq above, equal to or below B's: WRONG_STREAM, never ticked.
    accepted = s.counters["accepted"]
    for seq in (1000, 5, 2):
        n = send(d, seq, up, stream=nb2.stream, peer=a)
        assert (n.error, n.stream) == (WRONG_STREAM, nb2.stream)
    assert s.counters["accepted"] == accepted and s.stream_peer == b
    assert isinstance(send(d, 6, up, stream=nb2.stream, peer=b), Reply)  # B streams on


def test_offers_are_bounded_and_hellos_beyond_the_rate_use_up_no_numbers():
    d, s = make(open_stream=False)
    up = (5.0, 0.0, 30.0)
    answers = [send(d, 1, up, stream=0, peer=("10.0.0.1", port), now_ns=T0_NS)
               for port in range(100)]  # a hundred sources at one instant
    offered = [n.stream for n in answers if n is not None]
    burst = int(STREAM_NOTICE_BURST)
    assert offered == list(range(STREAM, STREAM + burst))
    assert s.next_stream == STREAM + burst
    # The latest MAX_OFFERS askers hold offers; an older one's was withdrawn: it hears so.
    assert len(s.offers) == MAX_OFFERS and s.offer == offered[-1]
    later = T0_NS + 10**9
    n = send(d, 2, up, stream=offered[0], peer=("10.0.0.1", 0), now_ns=later)
    assert (n.error, n.stream) == (WRONG_STREAM, offered[0])
    last = ("10.0.0.1", burst - 1)
    assert isinstance(send(d, 2, up, stream=offered[-1], peer=last, now_ns=later), Reply)


def test_a_v1_datagram_gets_a_bad_version_notice_in_v1_shape():
    d, _ = make()
    v1 = msgpack.packb([1, 1, 1, 5, 5000, [5.0, 0.0, 1.5], [0.0, 0.0, 0.0, 1.0], 60_000.0,
                        True, None, 4, None])
    out = d.handle(v1, T0_NS)
    assert msgpack.unpackb(out) == [1, 3, 1, 5, 5000, BAD_VERSION, None]
    with pytest.raises(ProtocolError) as info:
        decode_server_message(out)
    assert info.value.code == BAD_VERSION and info.value.header == (1, 5, 5000)
    later = msgpack.packb([3, 1, 1, 6, 6000, "anything", None, None])
    n = decode_server_message(d.handle(later, T0_NS))
    assert (n.error, n.stream, n.tag) == (BAD_VERSION, 0, None)
    assert d.counters["bad_version"] == 2


_ACTIONS = st.lists(st.sampled_from(["hello", "commit", "current", "old", "replay", "end",
                                     "junk"]), max_size=60)


@settings(max_examples=examples(60), deadline=None)
@given(actions=_ACTIONS)
def test_only_poses_of_the_committed_stream_are_ever_ticked(actions):
    """Random interleavings of hellos, commits, POSEs of old and current streams, replays
    and REST restarts: a POSE is ticked (answered with a REPLY) only if its stream is the one
    open after it arrived, committed from an offer the server made; stream numbers never
    repeat."""
    d, s = _SHARED_STREAMS
    s.end_stream()
    offers: list[int] = []  # every stream the server offered, in order
    opened: list[int] = []
    captured: list[bytes] = []
    seq = s.last_seq or 0
    for action in actions:
        seq += 1
        if action == "end":
            s.end_stream()
            continue
        stream = {"hello": 0, "commit": offers[-1] if offers else 0,
                  "current": s.stream, "old": opened[-2] if len(opened) > 1 else 1,
                  "junk": (seq * 2654435761) % (1 << 32) or 1}.get(action, 0)
        if action == "replay" and captured:
            data = captured[seq % len(captured)]
        else:
            data = encode_pose(Pose(1, seq, seq * 1000, (5.0, 0.0, 30.0), (0.0, 0.0, 0.0, 1.0),
                                    0.0, False, None, 0, stream), TAGGER)
            captured.append(data)
        sent = decode_pose(data).stream
        before = (s.stream, s.offer, s.counters["accepted"])
        out = d.handle(data, T0_NS + seq * 10**9)  # a second apart: no bucket limits
        m = None if out is None else decode_server_message(out)
        if isinstance(m, Reply):
            assert sent != 0 and sent in before[:2] and sent == s.stream
            assert s.counters["accepted"] == before[2] + 1
            if sent == before[1]:
                assert sent not in opened
                opened.append(sent)
        else:
            assert s.counters["accepted"] == before[2]
            if isinstance(m, Notice) and m.error == NEW_STREAM:
                assert m.stream not in opened and m.stream != 0
                if not offers or offers[-1] != m.stream:
                    assert m.stream not in offers
                    offers.append(m.stream)
    assert len(set(opened)) == len(opened)


_SHARED_STREAMS = make(open_stream=False)


# -- velocity from client timestamps -----------------------------------------------------------
def test_velocity_comes_from_client_timestamps_and_resets_on_gaps():
    d, s = make()
    first = send(d, 1, (5.0, 0.0, 30.0), t_us=1000)
    assert first.status & STATUS_STALE  # nothing to differentiate yet
    r = send(d, 2, (5.003, 0.0, 30.0), t_us=2000)
    assert not r.status & STATUS_STALE
    np.testing.assert_allclose(r.feed_velocity, (3.0, 0.0, 0.0), atol=1e-9)
    # Arrival time does not matter, the client's stamps do: 2 ms later, 6 µm → 3 mm/s.
    r = send(d, 3, (5.009, 0.0, 30.0), t_us=4000, now_ns=T0_NS + 2_500_000)
    np.testing.assert_allclose(r.feed_velocity, (3.0, 0.0, 0.0), atol=1e-9)
    # The same stamp twice (a coarse clock) keeps the estimate.
    r = send(d, 4, (5.009, 0.0, 30.0), t_us=4000)
    np.testing.assert_allclose(r.feed_velocity, (3.0, 0.0, 0.0), atol=1e-9)
    # A gap beyond gap_s (50 ms) resets it.
    r = send(d, 5, (5.5, 0.0, 30.0), t_us=104_000)
    assert r.status & STATUS_STALE and r.feed_velocity == (0.0, 0.0, 0.0)
    # So does a teleport (an estimate above max_speed_mm_s) and the reset flag.
    r = send(d, 6, (50.0, 0.0, 30.0), t_us=105_000)
    assert r.status & STATUS_STALE and s.counters["teleports"] == 1
    r = send(d, 7, (50.001, 0.0, 30.0), t_us=106_000, flags=FLAG_RESET_VELOCITY)
    assert r.status & STATUS_STALE
    # A velocity the client measured itself is used as it is, if plausible.
    r = send(d, 8, (50.0, 0.0, 30.0), t_us=107_000, velocity=(0.0, -2.0, 0.0))
    np.testing.assert_allclose(r.feed_velocity, (0.0, -2.0, 0.0), atol=1e-12)
    assert not r.status & STATUS_STALE
    r = send(d, 9, (50.0, 0.0, 30.0), t_us=108_000, velocity=(0.0, -1e5, 0.0))
    assert r.status & STATUS_STALE and r.feed_velocity == (0.0, 0.0, 0.0)
    # After a reset, a repeated stamp keeps the (zero, stale) estimate stale.
    r = send(d, 10, (50.0, 0.0, 30.0), t_us=108_000)
    assert r.status & STATUS_STALE


# -- authentication and bad input ---------------------------------------------------------------
def test_forged_and_foreign_datagrams_cannot_drive_a_session():
    d, s = make()
    good = encode_pose(Pose(1, 5, 5000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True,
                            stream=STREAM),
                       TAGGER)
    for bad in (
        encode_pose(Pose(1, 5, 5000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True)),
        encode_pose(Pose(1, 5, 5000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True),
                    Tagger(b"another key")),
        good[:20] + bytes([good[20] ^ 1]) + good[21:],
    ):
        out = d.handle(bad, T0_NS)
        notice = decode_server_message(out)
        assert isinstance(notice, Notice) and notice.error == BAD_TAG
        assert TAGGER.verify(out)  # the notice is the server's: tagged with the real key
    assert s.counters["accepted"] == 0 and s.engine.grid.version == 0
    assert d.counters["bad_tag"] == 3
    assert isinstance(decode_server_message(d.handle(good, T0_NS)), Reply)


def test_unknown_session_gets_an_untagged_notice_and_tiny_datagrams_none():
    d, _ = make()
    notice = send(d, 1, (0.0, 0.0, 0.0), session=99)
    assert isinstance(notice, Notice) and notice.error == UNKNOWN_SESSION
    assert notice.tag is None
    tiny = msgpack.packb([2, 1, 99, 1, 0])  # a readable header, shorter than any notice
    assert d.handle(tiny, T0_NS) is None
    assert d.handle(b"\x00garbage", T0_NS) is None
    assert d.handle(b"x" * 2000, T0_NS) is None
    assert d.counters["unknown_session"] == 1 and d.counters["malformed"] == 2
    assert d.counters["too_big"] == 1


def test_notices_never_outgrow_the_datagram_they_answer():
    d, _ = make()
    for version in (1, 2, 3):
        header = [version, 1, 7, 123456, 10**15]
        for extra in range(0, NOTICE_FIELDS + 8):
            data = msgpack.packb([*header, *([0] * extra)])
            out = d.handle(data, T0_NS + (version * 100 + extra) * 10**9)
            assert out is None or len(out) <= len(data)
    # A hello on a session without a key: its notice is shorter than the hello too.
    d, _ = make(key=None, open_stream=False)
    hello = encode_pose(Pose(1, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False))
    assert len(d.handle(hello, T0_NS)) <= len(hello)


def test_notices_are_rate_limited():
    d, _ = make()
    data = encode_pose(Pose(77, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False))
    answered = sum(d.handle(data, T0_NS) is not None for _ in range(500))
    assert answered == NOTICE_BURST
    assert d.counters["notices_suppressed"] == 500 - NOTICE_BURST


@pytest.mark.parametrize("field, value", [
    ("position", (math.nan, 0.0, 0.0)), ("position", (0.0, math.inf, 0.0)),
    ("orientation", (0.0, 0.0, 0.0, 0.0)), ("orientation", (0.0, 0.0, 0.0, 3.0)),
    ("rpm", math.inf), ("rpm", 1e9), ("velocity", (0.0, math.nan, 0.0)),
])
def test_unusable_values_get_an_error_reply_with_zero_force(field, value):
    d, _ = make()
    send(d, 1, (5.0, 0.0, 1.8))
    args = {"position": (5.003, 0.0, 1.8), "orientation": (0.0, 0.0, 0.0, 1.0),
            "rpm": 60_000.0, "velocity": None}
    args[field] = value
    r = send(d, 2, args["position"], orientation=args["orientation"], rpm=args["rpm"],
             velocity=args["velocity"])
    assert r.error == BAD_VALUE and r.force == (0.0, 0.0, 0.0) and r.status == 0
    assert r.vibration_amplitude == 0.0
    assert d.counters["bad_value"] == 1
    # The next good packet has no velocity across the bad one.
    assert send(d, 3, (5.006, 0.0, 1.8)).status & STATUS_STALE


def test_a_failing_tick_answers_internal_with_zero_force_and_the_loop_goes_on(monkeypatch):
    d, s = make()

    def broken(*args, **kwargs):
        raise RuntimeError("boom")

    monkeypatch.setattr(s.engine, "step_raw", broken)
    r = send(d, 1, (5.0, 0.0, 1.5))
    assert r.error == INTERNAL and r.force == (0.0, 0.0, 0.0)
    monkeypatch.undo()
    assert send(d, 2, (5.003, 0.0, 1.5)).error == OK
    assert d.counters["internal"] == 1


def _mutations(data: bytes):
    return st.one_of(
        st.binary(max_size=600),
        st.tuples(st.integers(0, len(data) - 1), st.integers(0, 255)).map(
            lambda iv: data[:iv[0]] + bytes([iv[1]]) + data[iv[0] + 1:]),
        st.integers(0, len(data)).map(lambda n: data[:n]),
        st.binary(min_size=1, max_size=40).map(lambda extra: data + extra),
    )


_VALID = encode_pose(Pose(1, 7, 7000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True,
                          stream=STREAM), TAGGER)
_SHARED = make()


@settings(max_examples=examples(400))
@given(_mutations(_VALID))
def test_handle_never_raises(data):
    d, _ = _SHARED
    out = d.handle(data, T0_NS)
    if out is not None and out[1:2] == b"\x01":  # the v1 answer to a v1 datagram
        assert msgpack.unpackb(out)[:2] == [1, 3] and msgpack.unpackb(out)[5] == BAD_VERSION
    elif out is not None:
        assert isinstance(decode_server_message(out), (Reply, Notice))


def test_snapshot_summarizes_tick_times_and_counts():
    d, _ = make()
    assert d.snapshot()["sessions"][1]["tick_p50_us"] is None  # nothing timed yet
    for k in range(1, 21):
        send(d, k, (5.0 + 0.003 * k, 0.0, 1.5))
    snap = d.snapshot()
    stats = snap["sessions"][1]
    assert snap["counters"]["replied"] == 20 and stats["accepted"] == 20
    assert 0.0 < stats["tick_p50_us"] <= stats["tick_p99_us"]
    assert "tick_times_us" not in stats
    assert stats["removed_mm3"]["cortical"] > 0.0


def test_warm_up_runs_every_path_and_leaves_the_session_as_given():
    d, s = make(open_stream=False)
    d.warm_up()
    assert (s.stream, s.offer, s.next_stream, s.last_seq) == (0, 0, STREAM, None)
    assert all(v == 0 for v in s.counters.values()) and s.ticks_timed == 0
    assert all(v == 0 for v in d.counters.values())
    assert send(d, 1, (5.0, 0.0, 30.0), stream=0).stream == STREAM


def test_accepted_says_whether_a_session_took_the_last_datagram():
    """What the loop gives a socket of its own for: only a POSE admitted in the open stream,
    never a hello, a refused stream, a replay or junk."""
    d, _ = make()
    assert send(d, 5, (5.0, 0.0, 30.0)) is not None and d.accepted
    for seq, stream in ((5, STREAM), (4, STREAM), (6, 0), (7, STREAM + 9)):
        send(d, seq, (5.0, 0.0, 30.0), stream=stream)
        assert not d.accepted, (seq, stream)
    d.handle(b"junk", T0_NS)
    assert not d.accepted


def test_client_rules_follow_only_verified_handshake_notices_that_match():
    """SessionRules (every Python client's handshake) against a real dispatcher: it adopts a
    NEW_STREAM that answers its own hello, ignores forged, foreign or late ones, and goes
    back to hello only on a verified WRONG_STREAM about its own stream."""
    from burrforce.client.udp import SessionRules
    from burrforce.proto.codec import encode_notice_values

    d, s = make(open_stream=False)
    rules = SessionRules(1, KEY, 100)

    def exchange(t_ns: int):
        _, data = rules.datagram((5.0, 0.0, 30.0), (0.0, 0.0, 0.0, 1.0), 0.0, False, None, 0,
                                 t_ns // 1000)
        out = d.handle(data, t_ns)
        return None if out is None else rules.accept(out, t_ns // 1000)

    forged = encode_notice_values(1, 100, 1, NEW_STREAM, 666, Tagger(b"attacker"))
    assert rules.accept(forged, 1) is None and rules.counters["bad_tag"] == 1
    _, hello = rules.datagram((5.0, 0.0, 30.0), IDENTITY, 0.0, False, None, 0, T0_NS // 1000)
    # An old NEW_STREAM replayed (a client that restarted its seqs): it echoes the seq of the
    # hello just sent, not its timestamp (SPEC 5.2): ignored.
    replayed = encode_notice_values(1, 100, T0_NS // 1000 - 5_000_000, NEW_STREAM, 555, TAGGER)
    assert rules.accept(replayed, 1).stream == 555 and rules.stream == 0
    n = rules.accept(d.handle(hello, T0_NS), 1)
    assert n.error == NEW_STREAM and rules.stream == STREAM  # the hello's own, adopted
    late = encode_notice_values(1, 100, 1, NEW_STREAM, 777, TAGGER)  # an old hello's answer
    rules.accept(late, 1)
    assert rules.stream == STREAM
    assert isinstance(exchange(T0_NS + 10**6).reply, Reply) and s.stream == STREAM
    other = encode_notice_values(1, 102, 1, WRONG_STREAM, STREAM + 5, TAGGER)
    rules.accept(other, 1)  # about another stream: nothing changes
    unverified = encode_notice_values(1, 102, 1, WRONG_STREAM, STREAM)
    assert rules.accept(unverified, 1) is None and rules.stream == STREAM
    s.end_stream()
    n = exchange(T0_NS + 2 * 10**6)
    assert n.error == WRONG_STREAM and rules.stream == 0
    assert exchange(T0_NS + 3 * 10**6).stream == STREAM + 1 and rules.stream == STREAM + 1
    assert (rules.counters["hellos"], rules.counters["streams"],
            rules.counters["wrong_stream"]) == (2, 2, 1)
    # Unkeyed sessions: nothing to verify, the same handshake.
    d2, _ = make(key=None, open_stream=False)
    open_rules = SessionRules(1, None, 1)
    _, hello = open_rules.datagram((5.0, 0.0, 30.0), IDENTITY, 0.0, False, None, 0, 1)
    open_rules.accept(d2.handle(hello, T0_NS), 1)
    assert open_rules.stream == STREAM


def _general_only(d: Dispatcher, data: bytes, t_ns: int):
    """``d.handle`` with the compiled decoder declining everything: the reference path."""
    from unittest import mock

    with mock.patch("burrforce.server.hotloop.dispatch.decode_pose_into",
                    lambda *args: False):
        return d.handle(data, t_ns)


def _comparable(out: bytes | None):
    if out is None or out[1:2] == b"\x01":
        return out
    m = decode_server_message(out)
    return m._replace(t_send_us=0, tag=None) if isinstance(m, Reply) else m  # t_send signed


_SEQUENCE = st.lists(st.tuples(st.integers(1, 40), st.integers(0, 3), st.data()), min_size=1,
                     max_size=12)


@settings(max_examples=examples(40), deadline=None)
@given(_SEQUENCE)
def test_the_compiled_path_answers_and_counts_exactly_as_the_general_decoder(steps):
    """The same datagrams (valid, mutated, replayed) through the compiled packet path and
    through the general decoder alone: the same answers (t_send_us aside), the same counters,
    the same session state."""
    fast, fs = make()
    ref, rs = make()
    for i, (seq, kind, data) in enumerate(steps):
        pose = Pose(1, seq, 10**6 + 1000 * seq, (5.0 + 0.003 * seq, 0.0, 1.5), IDENTITY,
                    60_000.0, True, (3.0, 0.0, 0.0) if kind == 3 else None, 0,
                    0 if kind == 2 else STREAM)
        datagram = encode_pose(pose, TAGGER)
        if kind == 1:
            datagram = data.draw(_mutations(datagram))
        t_ns = T0_NS + i * 10**6
        assert _comparable(fast.handle(datagram, t_ns)) == _comparable(
            _general_only(ref, datagram, t_ns))
        assert fast.accepted == ref.accepted
    assert fast.counters == ref.counters
    assert fs.counters == rs.counters and fs.last_seq == rs.last_seq
    assert (fs.stream, fs.offer, fs.next_stream) == (rs.stream, rs.offer, rs.next_stream)
