"""A session: one engine's burr cutting one bone, in that engine's frame and units.

:class:`Session` owns a stream's state (the handshake, the sequence, the velocity estimate),
the per-packet tick around its ``BoneEngine`` and its statistics. How it reads its engine's
packets is a ``session_config.SessionConfig``; where its per-packet state arrays live, private
memory or a control plane's telemetry file, is ``telemetry``.
"""

from __future__ import annotations

import itertools
import math
import secrets
import time

import numpy as np

from ...proto import frames
from ...proto.codec import encode_reply_values
from ...proto.messages import (
    BAD_VALUE,
    DUPLICATE,
    FLAG_NO_CARVE,
    OK,
    STALE,
    STATUS_CLAMPED,
    Pose,
)
from ...proto.sequence import seq_after
from ...proto.tag import Tagger
from ..bone.carve import TOUCH_FORBIDDEN
from ..bone.contact_status import contact_status
from ..bone.engine import BoneEngine
from ..bone.shaft import SHAFT_FORCE, SHAFT_TORQUE
from ..haptics.coupling import CLAMPED, PLACED, coupled_finish, coupled_predict, raw_limits
from ..haptics.layout import P_SHAFT_RADIUS, S_PERIOD
from ..haptics.stage import HapticStage
from ..haptics.transition import cut_weight
from ..model.kernels import (
    OUT_COMPONENTS,
    OUT_FORCE,
    OUT_POWER,
    OUT_TORQUE,
)
from .bucket import TokenBucket
from .session_config import ZERO3, SessionConfig, unit_vector
from .stages import (
    IN_BAD_VALUE,
    IN_RESET,
    IN_TELEPORT,
    K_A,
    K_B,
    K_DET,
    K_GAP_US,
    K_MAX_SPEED2,
    K_MIN_RPM,
    K_NOISE_MM,
    K_REPLY,
    K_SCALE,
    K_TOOL,
    K_VIB_FD_N,
    K_VIB_G,
    K_VIB_HARMONIC,
    K_VIB_ON,
    K_WINDOW_S,
    M_FLAGS,
    M_JUMPED,
    M_REPLY,
    M_RING,
    M_SESSION,
    M_STALE,
    M_STATUS,
    RAW_MODEL,
    RAW_TAGGED,
    W_AXIS,
    W_LAST_FORCE,
    W_P,
    W_RPM,
    W_V,
    W_VEL,
    new_state,
    pose_in,
    reply_error,
    reply_raw,
    ring_views,
)
from .telemetry import TICK_TIMES_KEPT, TelemetrySlot
from .wire import (
    P_FLAGS,
    P_SEQ,
    P_SPINDLE_ON,
    P_T_CLIENT,
    REPLY_FLOATS,
    REPLY_INTS,
    new_buffers,
    pose_arrays,
)

_TICK_EPOCHS = itertools.count(1)
_STREAM_MODULUS = 1 << 32
#: NEW_STREAM / WRONG_STREAM notices per second per session, and the burst: a handshake
#: needs one or two; a session of its own so a flood elsewhere cannot starve it.
STREAM_NOTICE_RATE_HZ = 100.0
STREAM_NOTICE_BURST = 20.0
#: Sources whose offers may await their commit at once; a hello from one more withdraws the
#: oldest offer (its commit is answered WRONG_STREAM, and that client asks again).
MAX_OFFERS = 4


class Session:
    """One engine streaming poses to one bone engine.

    Owns the stream and sequence state, the velocity estimate and the frame conversion:
    :meth:`hello` and :meth:`commit` open streams (SPEC.md 5.2), :meth:`admit` orders a
    stream's datagrams, :meth:`respond` answers each admitted one. Not thread-safe: the hot
    loop serializes access.

    Streams: ``stream`` is the open one (0: none), ``stream_peer`` the source address that
    opened it, ``offers`` the numbers hellos were answered with, by the source that asked,
    ``next_stream`` the next number to offer. Numbers only go forward (mod 2^32, skipping 0)
    and each goes to one source only, so two clients never share a stream, a stream once
    ended never opens again and a captured datagram of it is never answered. (A source is
    whatever the loop passes: an address; None in tests that call the dispatcher directly.)
    """

    def __init__(self, session_id: int, engine: BoneEngine, config: SessionConfig | None = None,
                 key: bytes | None = None, *, next_stream: int | None = None,
                 telemetry: TelemetrySlot | None = None) -> None:
        """``next_stream``: the first stream number to offer (nonzero uint32); None: a random
        one. The control plane passes the last journaled stream + 65536 after a restart, so
        no number offered before the restart is offered again. ``telemetry``: a slot of a
        telemetry file the per-packet state lives in (``hotloop.telemetry``); None: private
        arrays."""
        if not (isinstance(session_id, int) and 0 <= session_id < 1 << 32):
            raise ValueError(f"session id must be an unsigned 32-bit integer, got {session_id!r}")
        if next_stream is None:
            next_stream = secrets.randbelow(_STREAM_MODULUS - 1) + 1
        elif (isinstance(next_stream, bool) or not isinstance(next_stream, int)
              or not 0 < next_stream < _STREAM_MODULUS):
            raise ValueError(f"next_stream must be a nonzero unsigned 32-bit integer, got "
                             f"{next_stream!r}")
        self.id = session_id
        self.engine = engine
        self.key = key
        self.tagger = Tagger(key) if key is not None else None
        self.stream = 0
        self.stream_peer: object = None
        self.offers: dict[object, int] = {}
        self.next_stream = next_stream
        self.last_seq: int | None = None
        #: The session's notice buckets, for NEW_STREAM and WRONG_STREAM: two, so that
        #: replayed POSEs of closed streams (answered WRONG_STREAM) cannot use up the
        #: answers a client's hellos need.
        self.notice_buckets = (TokenBucket(STREAM_NOTICE_RATE_HZ, STREAM_NOTICE_BURST),
                               TokenBucket(STREAM_NOTICE_RATE_HZ, STREAM_NOTICE_BURST))
        self.counters = {"accepted": 0, "stale": 0, "duplicate": 0, "bad_value": 0,
                         "internal": 0, "hellos": 0, "streams": 0, "wrong_stream": 0,
                         "velocity_resets": 0, "teleports": 0}
        #: Where the state arrays live when the control plane samples them (or None).
        self.telemetry = telemetry
        self.tick_ns = (telemetry.tick_ns if telemetry is not None
                        else np.zeros(TICK_TIMES_KEPT, dtype=np.int64))
        self.ticks_timed = 0
        #: Names this session's count of timed ticks: a new session under the same id, or
        #: counters reset, start another (``Dispatcher.snapshot``'s ``tick_times_since``).
        self.tick_epoch = next(_TICK_EPOCHS)
        #: The bone's shared-memory counters, kept while publishing is off.
        self._shared_header = engine.grid.shared_header
        #: The per-packet stages' state (``stages``): constants, this packet's values in the
        #: grid frame, the velocity estimate's memory, the reply's values.
        # Same dtypes, shapes and contiguity either way: the kernels see the same types.
        self._k, self._m = new_state() if telemetry is None else (telemetry.k, telemetry.m)
        self._m[M_SESSION] = session_id
        # The bone engine's inputs are this packet's values where pose_in wrote them.
        self._c = self._k[W_P:W_P + 3]
        self._a = self._k[W_AXIS:W_AXIS + 3]
        self._v = self._k[W_V:W_V + 3]
        # Where the raw kernel keeps its reply, for the telemetry reader (_keep_reply).
        self._reply_f = self._k[K_REPLY:K_REPLY + REPLY_FLOATS]
        self._reply_i = self._m[M_REPLY:M_REPLY + REPLY_INTS]
        self.last_force_N = 0.0
        #: A ``record.Recorder`` taking every tick (``Recorder.attach``), or None.
        self.recorder = None
        self.configure(config if config is not None else SessionConfig())

    def configure(self, config: SessionConfig) -> None:
        """Apply ``config``. A change of frame, tool axis or placement restarts the velocity
        estimate and the haptic stage (positions before and after it do not compare); the
        stream and its sequence go on. Features and limits apply to the next packet."""
        frame = frames.frame(config.frame)
        grid = self.engine.grid
        old = getattr(self, "config", None)
        geometry_changed = old is None or (
            (old.frame, old.tool_axis, old.placement_position, old.placement_orientation)
            != (config.frame, config.tool_axis, config.placement_position,
                config.placement_orientation))
        self.config = config
        self.transform = frames.Transform(frame, config.placement_position,
                                          config.placement_orientation, grid.direction,
                                          grid.origin_mm)
        self.tool_axis = unit_vector("tool_axis", config.tool_axis or frame.tool_axis)
        # Read per packet: kept as plain attributes, not looked up through the config.
        self._gap_us = config.gap_s * 1e6
        self._max_speed2 = config.max_speed_mm_s ** 2
        self._model = config.model
        self._carve = config.carve
        self._vibration = config.vibration
        k = self._k
        k[K_A:K_A + 9] = self.transform.matrix.ravel()
        k[K_B:K_B + 3] = self.transform.offset_mm
        k[K_SCALE] = self.transform.scale
        k[K_DET] = self.transform.det
        k[K_TOOL:K_TOOL + 3] = self.tool_axis
        k[K_GAP_US] = self._gap_us
        k[K_MAX_SPEED2] = self._max_speed2
        vib = config.vibration
        k[K_VIB_ON] = 0.0 if vib is None else 1.0
        if vib is not None:
            k[K_VIB_FD_N], k[K_VIB_G], k[K_VIB_HARMONIC] = vib.fd_N, vib.g, vib.harmonic
        if old is None or (old.haptics, old.max_speed_mm_s) != (config.haptics,
                                                               config.max_speed_mm_s):
            self.haptics = HapticStage(config.haptics, grid.spacing_mm, config.max_speed_mm_s)
            # Its velocity ring lives in the stages' state (one kernel argument), empty.
            self._m[M_RING:M_RING + 2] = 0
            h = self.haptics
            h.ring_t, h.ring_p, h.ring_state = ring_views(self._k, self._m)
        #: The stage runs for the coupled output, or to hold the raw output to a device's
        #: limits; a raw session without a device skips it.
        self._coupled = self.haptics.coupled
        self._limited = self.haptics.limited
        #: The raw output without device limits: ``stages.reply_raw`` (unless recording).
        self._raw_fast = not (self._coupled or self._limited)
        self._m[M_FLAGS] = ((RAW_MODEL if config.model else 0)
                            | (RAW_TAGGED if self.tagger is not None else 0))
        k[K_NOISE_MM] = self.haptics.noise_mm
        k[K_WINDOW_S] = self.haptics.window_s
        self.engine_changed()
        if geometry_changed:
            self._forget_motion()

    def publish_bone(self, on: bool) -> None:
        """Keep (or stop) the counters that let the control plane read a shared bone while it
        is cut: two integer writes per carving tick."""
        header = self._shared_header if on else None
        if header is not None:
            header[1] = self.engine.grid.version  # carving went unpublished while it was off
        self.engine.grid.shared_header = header

    def publish_telemetry(self) -> None:
        """Once installed in the loop (under its lock): the control plane reads this session's
        telemetry slot from now on (no-op without one)."""
        if self.telemetry is not None:
            grid = self.engine.grid
            self.telemetry.activate(grid.origin_mm, grid.direction)

    def engine_changed(self) -> None:
        """After the engine's parameters changed: pick up what the hot path caches (the
        stream goes on; only the carve memory is reset by the engine)."""
        self._min_cutting_rpm = self.engine.params.min_cutting_rpm
        # The coupling compares contact areas with a sphere's: one of the burr's surface area.
        self._radius_mm = self.engine.contact_radius_mm
        self._k[K_MIN_RPM] = self._min_cutting_rpm
        # The coupled output's transition band above the minimum cutting speed, rpm.
        self._cutting_band_rpm = self._min_cutting_rpm * self.engine.params.cutting_band
        self.haptics.params[P_SHAFT_RADIUS] = self.engine.shaft.radius_mm

    def end_stream(self) -> None:
        """End the open stream and forget any offer: the client's next POSE gets
        WRONG_STREAM and it says hello again (REST ``restart-stream``)."""
        self.stream = 0
        self.stream_peer = None
        self.offers.clear()
        self.last_seq = None
        self._forget_motion()

    def _forget_motion(self) -> None:
        """Forget the velocity estimate, the haptic stage's state and the last carve."""
        m = self._m
        m[:M_RING] = 0  # the velocity estimate's (the ring itself: haptics.restart below)
        m[M_STALE] = 1
        #: The tool jumped (a teleport or FLAG_RESET_VELOCITY): the proxy follows it.
        m[M_JUMPED] = 1
        self._k[W_VEL:W_VEL + 3] = 0.0
        #: The client time of the last tick (the haptic stage's step), None before one.
        self._tick_t_us: int | None = None
        self.haptics.restart()
        self.engine.forget_last_carve()

    # -- streams (SPEC.md 5.2) ---------------------------------------------------------------
    @property
    def offer(self) -> int:
        """The latest offer still awaiting its commit (0: none)."""
        return next(reversed(self.offers.values()), 0)

    def hello(self, peer: object = None) -> int:
        """The stream offered to a hello from ``peer``: the same offer until it is committed,
        a number of its own to every other source (two clients asking at once never share
        one). The open stream is untouched (a replayed hello cannot disturb it)."""
        offer = self.offers.get(peer)
        if offer is None:
            if len(self.offers) >= MAX_OFFERS:
                del self.offers[next(iter(self.offers))]  # the oldest asker asks again
            offer = self.offers[peer] = self.next_stream
            self.next_stream = (self.next_stream + 1) % _STREAM_MODULUS or 1
        return offer

    def offered(self, stream: int, peer: object) -> bool:
        """``stream`` is the offer made to ``peer``: its POSE may commit it."""
        return stream != 0 and self.offers.get(peer) == stream

    def commit(self, peer: object = None) -> None:
        """A POSE from ``peer`` carried its offer: that stream becomes the open one, bound to
        ``peer``, with a fresh sequence and velocity state (its first tick is STALE unless
        the POSE carries a velocity); the previous stream and every other offer are over."""
        self.stream = self.offers[peer]
        self.stream_peer = peer
        self.offers.clear()
        self.last_seq = None
        self.counters["streams"] += 1
        self._forget_motion()

    def stream_notice_allowed(self, now_ns: int, wrong_stream: bool = False) -> bool:
        """Take a token from the session's NEW_STREAM (or WRONG_STREAM) notice bucket."""
        return self.notice_buckets[1 if wrong_stream else 0].take(now_ns)

    # -- the hot path -----------------------------------------------------------------------
    def admit(self, seq: int) -> int:
        """OK if ``seq`` is the newest the open stream has seen (any, on its first POSE), else
        STALE or DUPLICATE. Streams never restart by themselves (no idle restart): only a
        commit starts a sequence afresh."""
        last = self.last_seq
        if last is not None and not seq_after(seq, last):
            if seq == last:
                self.counters["duplicate"] += 1
                return DUPLICATE
            self.counters["stale"] += 1
            return STALE
        self.last_seq = seq
        return OK

    def respond_into(self, pose_i: np.ndarray, pose_f: np.ndarray, t_recv_ns: int,
                     tx: np.ndarray, tx_view: memoryview) -> tuple[memoryview | bytes, int]:
        """(reply, error code) for an admitted, authentic pose (``wire.P_*`` in ``pose_i``,
        ``pose_f``): a BAD_VALUE reply, with zero force, if its values are unusable.

        The reply is written into ``tx`` (uint8 (TX_BYTES,)) and returned as a slice of
        ``tx_view`` (valid until the next packet), or as bytes for the coupled and limited
        outputs and while recording.
        """
        counters = self.counters
        counters["accepted"] += 1
        code = pose_in(pose_i, pose_f, self._k, self._m)
        if code & (IN_BAD_VALUE | IN_RESET):
            if code & IN_BAD_VALUE:
                counters["bad_value"] += 1
                self.haptics.device_released()  # an error reply carries zero force
                return self.error_reply(pose_i, BAD_VALUE, t_recv_ns, tx, tx_view), BAD_VALUE
            counters["velocity_resets"] += 1
            if code & IN_TELEPORT:
                counters["teleports"] += 1
                self.engine.forget_last_carve()
        if not self._raw_fast or self.recorder is not None:
            values = self._tick(pose_i, pose_f, int(self._m[M_STATUS]), t_recv_ns)
            self._keep_reply(values)
            return encode_reply_values(values, self.tagger), OK
        # The raw output: what is numeric is one kernel; Python only calls the engine.
        engine = self.engine
        removed_mm3 = 0.0
        if self._model:
            carve = self._carve and not pose_i[P_FLAGS] & FLAG_NO_CARVE
            t0 = time.perf_counter_ns()
            removed = engine.step_raw(self._c, self._a, self._v, float(self._k[W_RPM]), carve)
            self.tick_ns[self.ticks_timed % TICK_TIMES_KEPT] = time.perf_counter_ns() - t0
            self.ticks_timed += 1
            engine.record_contact(t_recv_ns * 1e-9)
            if removed:
                removed_mm3 = engine.removed_this_tick_mm3()
        n = reply_raw(self._k, self._m, pose_i, engine.out, engine.shaft_out, engine.touch, tx,
                      removed_mm3, t_recv_ns // 1000, time.monotonic_ns() // 1000,
                      engine.grid.version)
        out = tx_view[:n]
        tagger = self.tagger
        if tagger is not None:
            tagger.sign(out)
        return out, OK

    def respond(self, pose: Pose, t_recv_ns: int) -> tuple[bytes, int]:
        """(encoded reply, error code) for an admitted, authentic ``pose`` (tools and tests;
        the dispatcher calls :meth:`respond_into`)."""
        _, pose_i, pose_f, tx, _ = new_buffers()
        pose_arrays(pose, pose_i, pose_f)
        out, error = self.respond_into(pose_i, pose_f, t_recv_ns, tx, memoryview(tx))
        return bytes(out), error

    def error_reply(self, pose_i: np.ndarray, error: int, t_recv_ns: int, tx: np.ndarray,
                    tx_view: memoryview) -> memoryview:
        """A reply carrying ``error`` and zero force, torque and vibration, to the pose in
        ``pose_i``, written into ``tx`` (as :meth:`respond_into`)."""
        n = reply_error(self._k, self._m, pose_i, error, t_recv_ns // 1000,
                        time.monotonic_ns() // 1000, self.engine.grid.version, tx)
        out = tx_view[:n]
        tagger = self.tagger
        if tagger is not None:
            tagger.sign(out)
        return out

    def _keep_reply(self, values: tuple) -> None:
        """Keep a reply built in Python (``_tick``'s values, wire order) where ``reply_raw``
        keeps its own, so live telemetry shows the coupled and limited outputs and recorded
        packets like the raw one: two array stores, ~2 µs on a path that takes far more."""
        (session, seq, t_client, t_recv, t_send, error, status, force, resistive, torque,
         power, amplitude, frequency, vib_axis, proxy_p, proxy_v, stiffness, damping,
         removed, bone_version, feed) = values
        self._reply_f[:] = (*force, *resistive, *torque, power, amplitude, frequency,
                            *vib_axis, *proxy_p, *proxy_v, stiffness, damping, removed, *feed)
        self._reply_i[:] = (session, seq, t_client, t_recv, t_send, error, status, bone_version)

    def _pose(self, pose_i: np.ndarray, pose_f: np.ndarray) -> Pose:
        """The decoded pose as a Pose (for the recorder; the tag is not kept)."""
        session, seq, t_us, flags, stream, on, has_v, _ = pose_i.tolist()
        f = pose_f.tolist()
        return Pose(session, seq, t_us, tuple(f[0:3]), tuple(f[3:7]), f[7], bool(on),
                    tuple(f[8:11]) if has_v else None, flags, stream)

    def _tick(self, pose_i: np.ndarray, pose_f: np.ndarray, status: int,
              t_recv_ns: int) -> tuple:
        """One tick of the coupled or limited output, or while recording, after
        ``stages.pose_in``: the reply's values in wire order (tag excluded). (The raw output
        is ``stages.reply_raw``.)"""
        tf = self.transform
        engine = self.engine
        k = self._k
        t_client_us = int(pose_i[P_T_CLIENT])
        spindle_on = bool(pose_i[P_SPINDLE_ON])
        rpm = float(k[W_RPM])
        ax, ay, az = k[W_AXIS:W_AXIS + 3].tolist()
        v = k[W_V:W_V + 3].tolist()
        removed_mm3 = 0.0
        force = resistive = torque = proxy_p = proxy_v = ZERO3
        power_w = cut_n = coupling_k = coupling_b = 0.0
        fx = fy = fz = 0.0
        if self._model:
            c, a, vv = self._c, self._a, self._v  # already the pose's p, axis and v
            coupled = self._coupled
            if coupled or self._limited:
                # The haptic stage steps by the client's clock; an interval it cannot use
                # (first tick, repeated or backwards time, a gap: a pause is not the packet
                # rate the coupling is tuned to) counts as the usual one.
                hs = self.haptics
                last_t = self._tick_t_us
                self._tick_t_us = t_client_us
                dt_us = -1 if last_t is None else t_client_us - last_t
                if 0 < dt_us <= self._gap_us:
                    dt_s = dt_us * 1e-6
                else:
                    dt_s = hs.state[S_PERIOD] if hs.state[S_PERIOD] > 0.0 else 1e-3
            if coupled:
                dp, dv = hs.device_p, hs.device_v
                dp[:] = c
                dv[:] = vv
                if coupled_predict(hs.state, hs.params, dp, dv, dt_s, bool(self._m[M_JUMPED]),
                                   c, vv) & PLACED:
                    engine.forget_last_carve()  # the proxy jumped: no sweep from before
                self._m[M_JUMPED] = 0
            carve = self._carve and not pose_i[P_FLAGS] & FLAG_NO_CARVE
            t0 = time.perf_counter_ns()
            removed = engine.step_raw(c, a, vv, rpm, carve)
            self.tick_ns[self.ticks_timed % TICK_TIMES_KEPT] = time.perf_counter_ns() - t0
            self.ticks_timed += 1
            out = engine.out.tolist()
            shaft = engine.shaft_out.tolist()
            status |= contact_status(engine.out, engine.shaft_out, engine.touch[TOUCH_FORBIDDEN])
            engine.record_contact(t_recv_ns * 1e-9)
            if removed:
                removed_mm3 = engine.removed_this_tick_mm3()
            fx, fy, fz = out[OUT_FORCE:OUT_FORCE + 3]
            tx, ty, tz = out[OUT_TORQUE:OUT_TORQUE + 3]
            resistive = out[OUT_COMPONENTS:OUT_COMPONENTS + 3]
            power_w = out[OUT_POWER] * 1e-3
            if coupled:
                # The proxy met its own cut (haptics.coupling), λ times the trial's in
                # magnitude; the hand feels the coupling, which also carries the shaft and
                # the rigid contacts.
                if coupled_finish(hs.state, hs.params, engine.out, engine.jacobian,
                                  engine.shaft_out,
                                  cut_weight(abs(rpm), self._min_cutting_rpm,
                                             self._cutting_band_rpm),
                                  self._radius_mm, hs.result, hs.scratch) & CLAMPED:
                    status |= STATUS_CLAMPED
                r = hs.result.tolist()
                lam = r[3]
                fx, fy, fz = r[14:17]
                tx, ty, tz = tx * lam, ty * lam, tz * lam
                resistive = r[17:20]
                power_w *= lam
                force = tf.direction_out(r[0:3])
                coupling_k = r[5] * tf.scale
                coupling_b = r[6] * tf.scale
                proxy_p = tf.point_out(r[7:10])
                proxy_v = tf.vector_out(r[10:13])
                v = r[10:13]  # the velocity that cut: the proxy's
            else:
                sx, sy, sz = shaft[SHAFT_FORCE:SHAFT_FORCE + 3]
                if self._limited:
                    f = hs.force
                    f[0], f[1], f[2] = fx + sx, fy + sy, fz + sz
                    if raw_limits(hs.state, hs.params, f, dt_s) & CLAMPED:
                        status |= STATUS_CLAMPED
                    force = tf.direction_out(f.tolist())
                else:
                    force = tf.direction_out((fx + sx, fy + sy, fz + sz))
            sx, sy, sz = shaft[SHAFT_TORQUE:SHAFT_TORQUE + 3]
            torque = tf.torque_out((tx + sx, ty + sy, tz + sz))
            resistive = tuple(resistive)
            cut_n = math.sqrt(fx * fx + fy * fy + fz * fz)
            if self.recorder is not None:
                self.recorder.record(t_recv_ns, self._pose(pose_i, pose_f), c, a, vv, rpm,
                                     carve, engine.out, engine.shaft_out, removed_mm3,
                                     engine.grid.version, status, force, torque)
        amplitude = frequency = 0.0
        vib = self._vibration
        if vib is not None and spindle_on and rpm != 0.0:
            # model.vibration.vibration(), inlined (see the docstring above).
            amplitude = math.hypot(vib.fd_N, vib.g * cut_n)
            frequency = abs(rpm) / 60.0 * vib.harmonic
        vib_axis = tf.direction_out((fx / cut_n, fy / cut_n, fz / cut_n) if cut_n > 0.0
                                    else (ax, ay, az))
        self.last_force_N = math.sqrt(force[0] ** 2 + force[1] ** 2 + force[2] ** 2)
        return (self.id, int(pose_i[P_SEQ]), t_client_us, t_recv_ns // 1000,
                time.monotonic_ns() // 1000, OK, status, force, resistive, torque, power_w,
                amplitude, frequency, vib_axis, proxy_p, proxy_v, coupling_k, coupling_b,
                removed_mm3, engine.grid.version, tf.vector_out(v))

    @property
    def last_force_N(self) -> float:
        """|force| of the last reply, N."""
        return float(self._k[W_LAST_FORCE])

    @last_force_N.setter
    def last_force_N(self, value: float) -> None:
        self._k[W_LAST_FORCE] = value

    # -- statistics -------------------------------------------------------------------------
    def reset_statistics(self) -> None:
        """Forget counters, tick times and the stream (after a warm-up)."""
        for name in self.counters:
            self.counters[name] = 0
        self.ticks_timed = 0
        self.tick_epoch = next(_TICK_EPOCHS)
        self.last_force_N = 0.0
        for bucket in self.notice_buckets:
            bucket.reset()
        self.end_stream()

    def tick_times_us(self) -> np.ndarray:
        """The last (up to TICK_TIMES_KEPT) model-stage times, oldest first, µs."""
        n = self.ticks_timed
        if n <= TICK_TIMES_KEPT:
            return self.tick_ns[:n] / 1e3
        return np.roll(self.tick_ns, -(n % TICK_TIMES_KEPT)) / 1e3

    def stats(self) -> dict[str, object]:
        """Counters and state, cheap enough to take between two packets; ``tick_times_us``
        holds the raw model-stage times (``Dispatcher.snapshot`` summarizes them)."""
        return {
            "session": self.id,
            "frame": self.config.frame,
            "authenticated": self.tagger is not None,
            "stream": self.stream,
            "next_stream": self.next_stream,
            **self.counters,
            "bone_version": self.engine.grid.version,
            "removed_mm3": self.engine.removed_mm3_by_material(),
            "forbidden_events": self.engine.tally.begun,
            "last_force_N": self.last_force_N,
            "ticks_timed": self.ticks_timed,
            "tick_epoch": self.tick_epoch,
            "tick_times_us": self.tick_times_us(),
        }
