"""A session's per-packet numeric stages, fused into two numba calls around the bone step.

:func:`pose_in`: value checks (SPEC.md 3.1), engine → grid frame, velocity (the client's,
or estimated from the client's timestamps, ``haptics.velocity``), the tool axis.
:func:`reply_raw`: the raw output (no coupling, no device limits) in the engine frame,
vibration, and the REPLY's bytes (``wire.encode_reply_into``).

Each is the same arithmetic, in the same order, as the Python it replaced (``Session._tick``
keeps it for the coupled and limited outputs): a packet arrives after the process slept for
most of a millisecond, with cold caches, and every Python call and object costs several times
its warm price, so the hot path pays a few kernel calls instead of a few hundred bytecodes.

State lives in two arrays per session (``new_state``), so a kernel call unboxes a few
arrays, not a dozen (numba's dispatch costs ~0.1–0.2 µs per argument):

    k  float64 (K_SIZE,)  per-session constants (K_*), this packet's work values (W_*), the
                          velocity ring's samples (K_RING_*) and the reply's floats (K_REPLY)
    m  int64   (M_SIZE,)  the velocity estimate's state, the ring's head and count, the
                          session's reply constants and the reply's integers (M_*)

The session's ``HapticStage`` ring arrays are views of these (``ring_views``).
"""

from __future__ import annotations

import math

import numpy as np

from ...proto.messages import (
    FLAG_RESET_VELOCITY,
    OK,
    STATUS_SLOW_SPINDLE,
    STATUS_STALE,
)
from ..bone.carve import TOUCH_FORBIDDEN
from ..bone.contact_status import contact_status
from ..bone.shaft import SHAFT_FORCE, SHAFT_TORQUE
from ..haptics.velocity import RING, reset, velocity_step
from ..hot_kernel import hot_kernel
from ..model.kernels import (
    OUT_COMPONENTS,
    OUT_FORCE,
    OUT_POWER,
    OUT_TORQUE,
)
from .wire import (
    P_FLAGS,
    P_HAS_VELOCITY,
    P_ORIENTATION,
    P_POSITION,
    P_RPM,
    P_SEQ,
    P_SPINDLE_ON,
    P_T_CLIENT,
    P_VELOCITY,
    R_AMPLITUDE,
    R_BONE_VERSION,
    R_ERROR,
    R_FEED,
    R_FORCE,
    R_FREQUENCY,
    R_POWER,
    R_REMOVED,
    R_RESISTIVE,
    R_SEQ,
    R_SESSION,
    R_STATUS,
    R_T_CLIENT,
    R_T_RECV,
    R_T_SEND,
    R_TORQUE,
    R_VIB_AXIS,
    REPLY_FLOATS,
    REPLY_INTS,
    encode_reply_into,
)

# k: constants, set by Session.configure / engine_changed.
K_A = 0  #: (9) engine → grid rotation A, row-major (frames.Transform)
K_B = 9  #: (3) grid offset, mm
K_SCALE = 12  #: mm per engine unit
K_DET = 13  #: det A (±1)
K_TOOL = 14  #: (3) the local tool axis, engine axes, unit
K_GAP_US = 17  #: a longer silence resets the velocity estimate, µs
K_MAX_SPEED2 = 18  #: (mm/s)²: faster is a teleport
K_MIN_RPM = 19  #: minimum cutting speed, rpm
K_NOISE_MM = 20  #: velocity estimator's position noise bound, mm
K_WINDOW_S = 21  #: velocity estimator's longest window, s
K_VIB_ON = 22  #: 1.0: vibration parameters are computed
K_VIB_FD_N = 23  #: vibration: the spindle's own amplitude, N
K_VIB_G = 24  #: vibration: amplitude per N of cutting force
K_VIB_HARMONIC = 25  #: vibration: frequency multiple of the spindle's
# k: this packet's values (grid frame, mm), written by pose_in.
W_P = 26  #: (3) burr centre
W_V = 29  #: (3) velocity, mm/s
W_AXIS = 32  #: (3) tool axis, unit
W_RPM = 35  #: rpm, 0 with the spindle off
W_VEL = 36  #: (3) the last velocity estimate (kept across a repeated client time)
W_LAST_FORCE = 39  #: |force| of the last reply, N
W_DEV = 40  #: (3) the velocity estimator's output, mm/s
K_RING_T = 43  #: (RING) velocity samples' times, s
K_RING_P = K_RING_T + RING  #: (RING, 3) velocity samples' positions, mm
K_REPLY = K_RING_P + 3 * RING  #: (REPLY_FLOATS) the reply's floats (wire.R_*)
K_SIZE = K_REPLY + REPLY_FLOATS

M_HAS_PREV = 0  #: 1: M_PREV_T holds the client time of the last velocity sample
M_PREV_T = 1  #: µs
M_T0 = 2  #: client time the velocity window counts from, µs
M_STALE = 3  #: 1: the kept estimate (W_VEL) is stale
M_JUMPED = 4  #: 1: the tool jumped (the coupled proxy follows it)
M_RING = 5  #: (2) the velocity ring's [head, count]
M_SESSION = 7  #: the session id
M_FLAGS = 8  #: RAW_* bits (the bone stage runs; replies are tagged)
M_STATUS = 9  #: this packet's STATUS_* bits so far (pose_in: stale, slow spindle)
M_REPLY = 10  #: (REPLY_INTS) the reply's integers (wire.R_*)
M_SIZE = M_REPLY + REPLY_INTS

# pose_in's result bits.
IN_BAD_VALUE = 1  #: a value fails SPEC 3.1: nothing else was computed
IN_RESET = 2  #: the velocity estimate was reset
IN_TELEPORT = 4  #: an implausible speed: a teleport (forget the last carve)
IN_STALE = 8  #: no velocity estimate this tick
IN_SLOW_SPINDLE = 16  #: spindle on, below the cutting speed

# reply_raw's flags.
RAW_MODEL = 1  #: the bone stage ran (engine outputs are this tick's)
RAW_TAGGED = 2  #: leave room for the tag

# Value limits (proto.codec; copied as plain floats for the kernel).
_MAX_COORDINATE = 1e9
_MAX_RPM = 1e7
_NORM_LOW = 0.5
_NORM_HIGH = 1.5


def new_state() -> tuple[np.ndarray, np.ndarray]:
    """``(k float64 (K_SIZE,), m int64 (M_SIZE,))``, zeros."""
    return np.zeros(K_SIZE), np.zeros(M_SIZE, np.int64)


def ring_views(k: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The velocity ring inside the state: ``(ring_t_s (RING,), ring_p_mm (RING, 3),
    ring_state (2,))`` as ``haptics.velocity.new_ring`` makes them."""
    return (k[K_RING_T:K_RING_T + RING], k[K_RING_P:K_RING_P + 3 * RING].reshape(RING, 3),
            m[M_RING:M_RING + 2])


@hot_kernel
def _in_range(f, start, count, limit):
    for i in range(start, start + count):
        if not -limit <= f[i] <= limit:  # false for NaN too
            return False
    return True


@hot_kernel
def _reset_velocity(k, m, t_us, ring_t, ring_p, ring_state, dev_v):
    reset(ring_state)
    m[M_T0] = t_us  # the window's times count from here: small numbers keep full precision
    velocity_step(ring_t, ring_p, ring_state, 0.0, k[W_P], k[W_P + 1], k[W_P + 2],
                  k[K_NOISE_MM], k[K_WINDOW_S], dev_v)
    m[M_HAS_PREV] = 1
    m[M_PREV_T] = t_us
    m[M_STALE] = 1
    for i in range(3):
        k[W_VEL + i] = 0.0
        k[W_V + i] = 0.0


@hot_kernel
def pose_in(pose_i, pose_f, k, m):
    """The decoded pose (``wire.P_*``) in the grid frame: W_P, W_V, W_AXIS, W_RPM of ``k``,
    and M_STATUS (STATUS_STALE, STATUS_SLOW_SPINDLE) of ``m``.

    pose_i int64 (POSE_INTS,), pose_f float64 (POSE_FLOATS,): the pose. k float64 (K_SIZE,),
    m int64 (M_SIZE,): the session's state. Returns IN_* bits; with IN_BAD_VALUE only the
    velocity's continuity is touched (none across an unusable pose).
    """
    ring_t = k[K_RING_T:K_RING_T + RING]
    ring_p = k[K_RING_P:K_RING_P + 3 * RING].reshape((RING, 3))
    ring_state = m[M_RING:M_RING + 2]
    dev_v = k[W_DEV:W_DEV + 3]
    # Values (proto.codec.check_pose_values).
    has_v = pose_i[P_HAS_VELOCITY] != 0
    if not (_in_range(pose_f, P_POSITION, 3, _MAX_COORDINATE)
            and _in_range(pose_f, P_ORIENTATION, 4, _MAX_COORDINATE)
            and (not has_v or _in_range(pose_f, P_VELOCITY, 3, _MAX_COORDINATE))
            and -_MAX_RPM <= pose_f[P_RPM] <= _MAX_RPM):
        m[M_HAS_PREV] = 0
        return IN_BAD_VALUE
    x = pose_f[P_ORIENTATION]
    y = pose_f[P_ORIENTATION + 1]
    z = pose_f[P_ORIENTATION + 2]
    w = pose_f[P_ORIENTATION + 3]
    qn = math.sqrt(x * x + y * y + z * z + w * w)
    if not _NORM_LOW <= qn <= _NORM_HIGH:
        m[M_HAS_PREV] = 0
        return IN_BAD_VALUE
    a0, a1, a2 = k[K_A], k[K_A + 1], k[K_A + 2]
    a3, a4, a5 = k[K_A + 3], k[K_A + 4], k[K_A + 5]
    a6, a7, a8 = k[K_A + 6], k[K_A + 7], k[K_A + 8]
    s = k[K_SCALE]
    # Position (Transform.point_in).
    px, py, pz = pose_f[P_POSITION] * s, pose_f[P_POSITION + 1] * s, pose_f[P_POSITION + 2] * s
    k[W_P] = a0 * px + a1 * py + a2 * pz + k[K_B]
    k[W_P + 1] = a3 * px + a4 * py + a5 * pz + k[K_B + 1]
    k[W_P + 2] = a6 * px + a7 * py + a8 * pz + k[K_B + 2]
    # Velocity (Session._velocity).
    code = 0
    t_us = pose_i[P_T_CLIENT]
    if has_v:
        ex, ey, ez = pose_f[P_VELOCITY], pose_f[P_VELOCITY + 1], pose_f[P_VELOCITY + 2]
        vx = (a0 * ex + a1 * ey + a2 * ez) * s
        vy = (a3 * ex + a4 * ey + a5 * ez) * s
        vz = (a6 * ex + a7 * ey + a8 * ez) * s
        estimated = True
    else:
        estimated = False
        if m[M_HAS_PREV] == 0 or pose_i[P_FLAGS] & FLAG_RESET_VELOCITY:
            m[M_JUMPED] = m[M_HAS_PREV]
            _reset_velocity(k, m, t_us, ring_t, ring_p, ring_state, dev_v)
            code |= IN_RESET | IN_STALE
        else:
            dt_us = t_us - m[M_PREV_T]
            if dt_us == 0:  # a coarse client clock: keep the estimate, measure over two
                for i in range(3):
                    k[W_V + i] = k[W_VEL + i]
                if m[M_STALE] != 0:
                    code |= IN_STALE
            elif dt_us < 0 or dt_us > k[K_GAP_US]:
                _reset_velocity(k, m, t_us, ring_t, ring_p, ring_state, dev_v)
                code |= IN_RESET | IN_STALE
            else:
                velocity_step(ring_t, ring_p, ring_state, (t_us - m[M_T0]) * 1e-6, k[W_P],
                              k[W_P + 1], k[W_P + 2], k[K_NOISE_MM], k[K_WINDOW_S], dev_v)
                vx, vy, vz = dev_v[0], dev_v[1], dev_v[2]
                estimated = True
    if estimated:
        if vx * vx + vy * vy + vz * vz > k[K_MAX_SPEED2]:
            m[M_JUMPED] = 1
            _reset_velocity(k, m, t_us, ring_t, ring_p, ring_state, dev_v)
            code |= IN_TELEPORT | IN_RESET | IN_STALE
        else:
            m[M_HAS_PREV] = 1
            m[M_PREV_T] = t_us
            m[M_STALE] = 0
            k[W_VEL], k[W_VEL + 1], k[W_VEL + 2] = vx, vy, vz
            k[W_V], k[W_V + 1], k[W_V + 2] = vx, vy, vz
    # Tool axis (frames.quat_rotate, Transform.direction_in, normalized).
    x, y, z, w = x / qn, y / qn, z / qn, w / qn
    ux, uy, uz = k[K_TOOL], k[K_TOOL + 1], k[K_TOOL + 2]
    tx = 2.0 * (y * uz - z * uy)
    ty = 2.0 * (z * ux - x * uz)
    tz = 2.0 * (x * uy - y * ux)
    rx = ux + w * tx + (y * tz - z * ty)
    ry = uy + w * ty + (z * tx - x * tz)
    rz = uz + w * tz + (x * ty - y * tx)
    ax = a0 * rx + a1 * ry + a2 * rz
    ay = a3 * rx + a4 * ry + a5 * rz
    az = a6 * rx + a7 * ry + a8 * rz
    norm = math.sqrt(ax * ax + ay * ay + az * az)
    k[W_AXIS], k[W_AXIS + 1], k[W_AXIS + 2] = ax / norm, ay / norm, az / norm
    rpm = pose_f[P_RPM] if pose_i[P_SPINDLE_ON] != 0 else 0.0
    k[W_RPM] = rpm
    status = STATUS_STALE if code & IN_STALE else 0
    if pose_i[P_SPINDLE_ON] != 0 and 0.0 < abs(rpm) < k[K_MIN_RPM]:
        code |= IN_SLOW_SPINDLE
        status |= STATUS_SLOW_SPINDLE
    m[M_STATUS] = status
    return code


@hot_kernel
def _out3(k, x, y, z, reply_f, at, factor):
    """reply_f[at:at+3] = Aᵀ (x, y, z) · factor (Transform.direction_out, then scaled)."""
    ex = k[K_A] * x + k[K_A + 3] * y + k[K_A + 6] * z
    ey = k[K_A + 1] * x + k[K_A + 4] * y + k[K_A + 7] * z
    ez = k[K_A + 2] * x + k[K_A + 5] * y + k[K_A + 8] * z
    if factor == 1.0:  # a force or direction: no multiplication (bit-exact with Python's)
        reply_f[at], reply_f[at + 1], reply_f[at + 2] = ex, ey, ez
    else:
        reply_f[at], reply_f[at + 1], reply_f[at + 2] = ex * factor, ey * factor, ez * factor


@hot_kernel
def _reply_ints(reply_i, m, pose_i, error, status, t_recv_us, t_send_us, bone_version):
    """A REPLY's integers (wire R_*): the session and the pose answered, the server's clock
    at receipt and send (µs), the error code, the status bits and the bone's version."""
    reply_i[R_SESSION] = m[M_SESSION]
    reply_i[R_SEQ] = pose_i[P_SEQ]
    reply_i[R_T_CLIENT] = pose_i[P_T_CLIENT]
    reply_i[R_T_RECV] = t_recv_us
    reply_i[R_T_SEND] = t_send_us
    reply_i[R_ERROR] = error
    reply_i[R_STATUS] = status
    reply_i[R_BONE_VERSION] = bone_version


@hot_kernel
def reply_raw(k, m, pose_i, out, shaft_out, touch, tx, removed_mm3, t_recv_us, t_send_us,
              bone_version):
    """The raw output of a tick in the engine frame, encoded into ``tx``; returns its length.

    k, m: the session's state after :func:`pose_in`; pose_i: the pose. out, shaft_out,
    touch: the bone engine's outputs (read only with RAW_MODEL in m[M_FLAGS]). tx uint8
    (TX_BYTES,): the datagram (with RAW_TAGGED, 16 zero bytes at its end for the MAC).
    removed_mm3: bone removed, mm³; t_recv_us, t_send_us: the server's clock, µs. |force|
    goes to k[W_LAST_FORCE].
    """
    flags = m[M_FLAGS]
    status = m[M_STATUS]
    reply_f = k[K_REPLY:K_REPLY + REPLY_FLOATS]
    reply_i = m[M_REPLY:M_REPLY + REPLY_INTS]
    s = k[K_SCALE]
    fx = fy = fz = 0.0
    for i in range(R_FORCE, R_FEED + 3):
        reply_f[i] = 0.0
    if flags & RAW_MODEL:
        status |= contact_status(out, shaft_out, touch[TOUCH_FORBIDDEN])
        fx, fy, fz = out[OUT_FORCE], out[OUT_FORCE + 1], out[OUT_FORCE + 2]
        for i in range(3):
            reply_f[R_RESISTIVE + i] = out[OUT_COMPONENTS + i]
        reply_f[R_POWER] = out[OUT_POWER] * 1e-3
        _out3(k, fx + shaft_out[SHAFT_FORCE], fy + shaft_out[SHAFT_FORCE + 1],
              fz + shaft_out[SHAFT_FORCE + 2], reply_f, R_FORCE, 1.0)
        # Transform.torque_out: direction_out, then · det / scale.
        _out3(k, out[OUT_TORQUE] + shaft_out[SHAFT_TORQUE],
              out[OUT_TORQUE + 1] + shaft_out[SHAFT_TORQUE + 1],
              out[OUT_TORQUE + 2] + shaft_out[SHAFT_TORQUE + 2], reply_f, R_TORQUE,
              k[K_DET] / s)
    cut_n = math.sqrt(fx * fx + fy * fy + fz * fz)
    rpm = k[W_RPM]
    if k[K_VIB_ON] != 0.0 and pose_i[P_SPINDLE_ON] != 0 and rpm != 0.0:
        reply_f[R_AMPLITUDE] = math.hypot(k[K_VIB_FD_N], k[K_VIB_G] * cut_n)
        reply_f[R_FREQUENCY] = abs(rpm) / 60.0 * k[K_VIB_HARMONIC]
    if cut_n > 0.0:
        _out3(k, fx / cut_n, fy / cut_n, fz / cut_n, reply_f, R_VIB_AXIS, 1.0)
    else:
        _out3(k, k[W_AXIS], k[W_AXIS + 1], k[W_AXIS + 2], reply_f, R_VIB_AXIS, 1.0)
    # Transform.vector_out divides by the scale.
    ex = k[K_A] * k[W_V] + k[K_A + 3] * k[W_V + 1] + k[K_A + 6] * k[W_V + 2]
    ey = k[K_A + 1] * k[W_V] + k[K_A + 4] * k[W_V + 1] + k[K_A + 7] * k[W_V + 2]
    ez = k[K_A + 2] * k[W_V] + k[K_A + 5] * k[W_V + 1] + k[K_A + 8] * k[W_V + 2]
    reply_f[R_FEED], reply_f[R_FEED + 1], reply_f[R_FEED + 2] = ex / s, ey / s, ez / s
    reply_f[R_REMOVED] = removed_mm3
    f0, f1, f2 = reply_f[R_FORCE], reply_f[R_FORCE + 1], reply_f[R_FORCE + 2]
    k[W_LAST_FORCE] = math.sqrt(f0 ** 2 + f1 ** 2 + f2 ** 2)
    _reply_ints(reply_i, m, pose_i, OK, status, t_recv_us, t_send_us, bone_version)
    return encode_reply_into(tx, reply_i, reply_f, flags & RAW_TAGGED != 0)


@hot_kernel
def reply_error(k, m, pose_i, error, t_recv_us, t_send_us, bone_version, tx):
    """An error REPLY (zero force, torque, vibration: SPEC 3.4) to ``pose_i`` encoded into
    ``tx``; its length."""
    reply_f = k[K_REPLY:K_REPLY + REPLY_FLOATS]
    reply_i = m[M_REPLY:M_REPLY + REPLY_INTS]
    for i in range(REPLY_FLOATS):
        reply_f[i] = 0.0
    _reply_ints(reply_i, m, pose_i, error, 0, t_recv_us, t_send_us, bone_version)
    return encode_reply_into(tx, reply_i, reply_f, m[M_FLAGS] & RAW_TAGGED != 0)

