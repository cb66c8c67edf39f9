"""The protocol in front of the sessions, without sockets: Dispatcher.handle on real engines."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from burrforce.proto import frames
from burrforce.proto.codec import decode_server_message, encode_pose
from burrforce.proto.messages import (
    BAD_TAG,
    BAD_VALUE,
    FLAG_NEW_STREAM,
    FLAG_RESET_VELOCITY,
    INTERNAL,
    NOTICE_FIELDS,
    OK,
    STATUS_CONTACT,
    STATUS_CUTTING,
    STATUS_SLOW_SPINDLE,
    STATUS_STALE,
    UNKNOWN_SESSION,
    Notice,
    Pose,
    Reply,
)
from burrforce.proto.tag import Tagger
from burrforce.server.bone import BoneEngine, workpiece_block
from burrforce.server.hotloop import Dispatcher, Session, SessionConfig
from burrforce.server.hotloop.dispatch import NOTICE_BURST
from burrforce.server.model import CuttingModel, CuttingParams
from burrforce.server.model.cases import CuttingCase

KEY = bytes(range(32))
TAGGER = Tagger(KEY)
T0_NS = 10**12
ALPHA_DEG = 60.0


def tilted(alpha_deg: float = ALPHA_DEG) -> tuple[float, float, float, float]:
    """Quaternion taking +z to the thesis's tool axis (−cos α, 0, sin α)."""
    beta = math.radians(alpha_deg - 90.0)
    return (0.0, math.sin(beta / 2.0), 0.0, math.cos(beta / 2.0))


def make(voxel_mm: float = 0.25, frame: str = "si_mm", key: bytes | None = KEY,
         **config) -> tuple[Dispatcher, Session]:
    grid = workpiece_block(voxel_mm)
    session = Session(1, BoneEngine(grid), SessionConfig(frame=frame, **config), key)
    d = Dispatcher()
    d.add(session)
    return d, session


def send(d: Dispatcher, seq: int, position, *, t_us: int | None = None, key=KEY,
         orientation=(0.0, 0.0, 0.0, 1.0), rpm=60_000.0, on=True, velocity=None, flags=0,
         now_ns: int | None = None, session: int = 1):
    t_us = seq * 1000 if t_us is None else t_us
    pose = Pose(session, seq, t_us, tuple(position), tuple(orientation), rpm, on, velocity,
                flags)
    data = encode_pose(pose, Tagger(key) if key is not None else None)
    out = d.handle(data, T0_NS + t_us * 1000 if now_ns is None else now_ns)
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
        replies.append(send(d, k, p, orientation=q, flags=FLAG_NEW_STREAM if k == 1 else 0))
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


def test_a_new_stream_starts_with_the_flag_or_after_idling():
    d, s = make(idle_restart_s=0.5)
    assert send(d, 1000, (5.0, 0.0, 30.0)) is not None
    assert send(d, 1, (5.0, 0.0, 30.0), t_us=1_001_000) is None  # stale: same stream
    assert send(d, 2, (5.0, 0.0, 30.0), t_us=1_002_000, flags=FLAG_NEW_STREAM) is not None
    assert send(d, 3, (5.0, 0.0, 30.0), t_us=1_003_000) is not None
    # 0.6 s later (server clock): any sequence number starts a new stream.
    assert send(d, 1, (5.0, 0.0, 30.0), t_us=1_603_000) is not None
    assert s.counters["restarts"] == 2


def test_a_replayed_new_stream_datagram_is_stale_by_its_clock():
    d, s = make()
    captured = encode_pose(Pose(1, 5, 5_000, (5.0, 0.0, 30.0), (0.0, 0.0, 0.0, 1.0), 0.0, True,
                                None, FLAG_NEW_STREAM), TAGGER)
    assert d.handle(captured, T0_NS + 5_000_000) is not None
    for k in range(6, 50):
        assert send(d, k, (5.0, 0.0, 30.0)) is not None
    assert d.handle(captured, T0_NS + 50_000_000) is None  # replayed within the stream
    assert s.counters["restarts"] == 0 and d.counters["stale"] == 1


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
    good = encode_pose(Pose(1, 5, 5000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True),
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
    tiny = msgpack.packb([1, 1, 99, 1, 0])  # a readable header, shorter than any notice
    assert d.handle(tiny, T0_NS) is None
    assert d.handle(b"\x00garbage", T0_NS) is None
    assert d.handle(b"x" * 2000, T0_NS) is None
    assert d.counters["unknown_session"] == 1 and d.counters["malformed"] == 2
    assert d.counters["too_big"] == 1


def test_notices_never_outgrow_the_datagram_they_answer():
    d, _ = make()
    header = [1, 1, 7, 123456, 10**15]
    for extra in range(0, NOTICE_FIELDS + 8):
        data = msgpack.packb([*header, *([0] * extra)])
        out = d.handle(data, T0_NS + extra * 10**9)
        assert out is None or len(out) <= len(data)


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


_VALID = encode_pose(Pose(1, 7, 7000, (5.0, 0.0, 1.5), (0.0, 0.0, 0.0, 1.0), 60_000.0, True),
                     TAGGER)
_SHARED = make()


@settings(max_examples=400)
@given(_mutations(_VALID))
def test_handle_never_raises(data):
    d, _ = _SHARED
    out = d.handle(data, T0_NS)
    if out is not None:
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
