"""The hot loop's compiled packet path: the canonical POSE decoded, the REPLY encoded.

Server-only (numba), so ``proto`` stays importable by clients without it. Byte layouts are
SPEC.md's; ``proto.codec`` stays the reference: a datagram :func:`decode_pose_into` does not
recognise as a canonical POSE goes to ``proto.codec.decode_pose``, which accepts every other
valid form and says what is wrong with the rest, so every error code and counter is the
general decoder's. :func:`encode_reply_into` writes the bytes ``proto.codec.encode_reply``
writes (tests/test_proto_codec.py checks both against the reference on random messages).

Canonical POSE (what every SDK and ``encode_pose`` send): ``9d 02 01``, the header integers
in any unsigned form, floats as float 64 (``cb``), arrays as fixarrays, the velocity nil or a
fixarray of 3 float 64, the tag nil or ``c4 10`` + 16 bytes, nothing after it.
"""

from __future__ import annotations

import numpy as np

from ...proto.codec import encode_pose
from ...proto.messages import (
    MAX_REPLY_BYTES,
    MAX_REQUEST_BYTES,
    POSE,
    REPLY,
    VERSION,
    Pose,
)
from ..hot_kernel import hot_kernel

# Decoded POSE, integers: int64 (POSE_INTS,).
P_SESSION = 0
P_SEQ = 1
P_T_CLIENT = 2
P_FLAGS = 3
P_STREAM = 4
P_SPINDLE_ON = 5
P_HAS_VELOCITY = 6  #: 1: a velocity was sent (P_VELOCITY holds it); 0: nil.
P_HAS_TAG = 7  #: 1: the tag is a 16-byte bin (the datagram's last 16 bytes); 0: nil.
POSE_INTS = 8
# Decoded POSE, floats: float64 (POSE_FLOATS,), engine frame and units.
P_POSITION = 0  # 3
P_ORIENTATION = 3  # 4 (x, y, z, w)
P_RPM = 7
P_VELOCITY = 8  # 3 (zero when nil)
POSE_FLOATS = 11

# REPLY integers: int64 (REPLY_INTS,), in wire order.
R_SESSION = 0
R_SEQ = 1
R_T_CLIENT = 2
R_T_RECV = 3
R_T_SEND = 4
R_ERROR = 5
R_STATUS = 6
R_BONE_VERSION = 7
REPLY_INTS = 8
# REPLY floats: float64 (REPLY_FLOATS,), in wire order (bone_version sits between removed
# and feed on the wire).
R_FORCE = 0  # 3
R_RESISTIVE = 3  # 3
R_TORQUE = 6  # 3
R_POWER = 9
R_AMPLITUDE = 10
R_FREQUENCY = 11
R_VIB_AXIS = 12  # 3
R_PROXY_P = 15  # 3
R_PROXY_V = 18  # 3
R_STIFFNESS = 21
R_DAMPING = 22
R_REMOVED = 23
R_FEED = 24  # 3
REPLY_FLOATS = 27

#: Receive buffer, bytes: one more than a request may have, so an oversized datagram shows
#: as such (the kernel truncates it to the buffer).
RX_BYTES = MAX_REQUEST_BYTES + 1
TX_BYTES = MAX_REPLY_BYTES

_UINT32_END = 1 << 32


def new_buffers() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rx uint8 (RX_BYTES,), pose_i int64 (POSE_INTS,), pose_f float64 (POSE_FLOATS,),
    tx uint8 (TX_BYTES,), reply_i int64 (REPLY_INTS,))``; reply floats are per session."""
    return (np.zeros(RX_BYTES, np.uint8), np.zeros(POSE_INTS, np.int64),
            np.zeros(POSE_FLOATS, np.float64), np.zeros(TX_BYTES, np.uint8),
            np.zeros(REPLY_INTS, np.int64))


def pose_arrays(pose: Pose, pose_i: np.ndarray, pose_f: np.ndarray) -> None:
    """Fill ``pose_i``, ``pose_f`` (as :func:`decode_pose_into` does) from a decoded Pose
    (the general decoder's: a POSE in any other valid form)."""
    velocity = pose.velocity
    pose_i[:] = (pose.session, pose.seq, pose.t_client_us, pose.flags, pose.stream,
                 pose.spindle_on, velocity is not None, pose.tag is not None)
    pose_f[:] = (*pose.position, *pose.orientation, pose.rpm,
                 *(velocity if velocity is not None else (0.0, 0.0, 0.0)))


@hot_kernel
def _uint(buf, i, n):
    """(value, next index) of the msgpack unsigned integer at ``buf[i]``; next index −1 if
    it is not one (or is ≥ 2⁶³, which no POSE field may be)."""
    if i >= n:
        return 0, -1
    b = buf[i]
    if b < 0x80:
        return np.int64(b), i + 1
    if b == 0xCC:
        width = 1
    elif b == 0xCD:
        width = 2
    elif b == 0xCE:
        width = 4
    elif b == 0xCF:
        width = 8
        if i + 1 < n and buf[i + 1] >= 0x80:
            return 0, -1
    else:
        return 0, -1
    if i + 1 + width > n:
        return 0, -1
    v = np.int64(0)
    for k in range(width):
        v = (v << 8) | np.int64(buf[i + 1 + k])
    return v, i + 1 + width


@hot_kernel
def _float64(buf, i, n, bits, k):
    """Read the float 64 (``cb`` + 8 big-endian bytes) at ``buf[i]`` into ``bits[k]`` (a
    uint64 view of the float output); the next index, or −1 if it is not one."""
    if i + 9 > n or buf[i] != 0xCB:
        return -1
    v = np.uint64(0)
    for j in range(1, 9):
        v = (v << np.uint64(8)) | np.uint64(buf[i + j])
    bits[k] = v
    return i + 9


@hot_kernel
def decode_pose_into(buf, n, pose_i, pose_f):
    """Decode ``buf[:n]`` if it is a canonical POSE (module docstring) with every field in
    range (as ``proto.codec.decode_pose`` checks them); values are not checked.

    buf: uint8 (≥ n,), the datagram. pose_i: int64 (POSE_INTS,), pose_f: float64
    (POSE_FLOATS,) receive the fields (P_*). Returns True if decoded; False: the datagram
    is something else (maybe valid, maybe not) for the general decoder, and the outputs are
    garbage.
    """
    if n > MAX_REQUEST_BYTES or n < 3 or buf[0] != 0x9D or buf[1] != VERSION \
            or buf[2] != POSE:
        return False
    bits = pose_f.view(np.uint64)
    i = 3
    for k in range(3):  # session, seq, t_client_us
        v, i = _uint(buf, i, n)
        if i < 0 or (k < 2 and v >= _UINT32_END):
            return False
        pose_i[k] = v
    if i >= n or buf[i] != 0x93:
        return False
    i += 1
    for k in range(3):
        i = _float64(buf, i, n, bits, P_POSITION + k)
        if i < 0:
            return False
    if i >= n or buf[i] != 0x94:
        return False
    i += 1
    for k in range(4):
        i = _float64(buf, i, n, bits, P_ORIENTATION + k)
        if i < 0:
            return False
    i = _float64(buf, i, n, bits, P_RPM)
    if i < 0 or i >= n:
        return False
    if buf[i] == 0xC3:
        pose_i[P_SPINDLE_ON] = 1
    elif buf[i] == 0xC2:
        pose_i[P_SPINDLE_ON] = 0
    else:
        return False
    i += 1
    if i >= n:
        return False
    if buf[i] == 0xC0:
        pose_i[P_HAS_VELOCITY] = 0
        for k in range(3):
            pose_f[P_VELOCITY + k] = 0.0
        i += 1
    elif buf[i] == 0x93:
        pose_i[P_HAS_VELOCITY] = 1
        i += 1
        for k in range(3):
            i = _float64(buf, i, n, bits, P_VELOCITY + k)
            if i < 0:
                return False
    else:
        return False
    for k in (P_FLAGS, P_STREAM):
        v, i = _uint(buf, i, n)
        if i < 0 or v >= _UINT32_END:
            return False
        pose_i[k] = v
    if i + 1 == n and buf[i] == 0xC0:
        pose_i[P_HAS_TAG] = 0
        return True
    if i + 18 == n and buf[i] == 0xC4 and buf[i + 1] == 16:
        pose_i[P_HAS_TAG] = 1
        return True
    return False


@hot_kernel
def _put_int(out, i, v):
    """msgpack's smallest form of the integer ``v`` (as msgpack-python packs a Python int)
    at ``out[i]``; the next index."""
    if v >= 0:
        if v < 0x80:
            out[i] = v
            return i + 1
        if v < 0x100:
            out[i] = 0xCC
            width = 1
        elif v < 0x10000:
            out[i] = 0xCD
            width = 2
        elif v < 0x100000000:
            out[i] = 0xCE
            width = 4
        else:
            out[i] = 0xCF
            width = 8
    else:
        if v >= -32:
            out[i] = v & 0xFF
            return i + 1
        if v >= -0x80:
            out[i] = 0xD0
            width = 1
        elif v >= -0x8000:
            out[i] = 0xD1
            width = 2
        elif v >= -0x80000000:
            out[i] = 0xD2
            width = 4
        else:
            out[i] = 0xD3
            width = 8
    for k in range(width):
        out[i + width - k] = (v >> (8 * k)) & 0xFF
    return i + 1 + width


@hot_kernel
def _put_floats(out, i, bits, start, count, array):
    """``count`` float 64s from ``bits[start:]`` (a uint64 view), as a fixarray if ``array``;
    the next index."""
    if array:
        out[i] = 0x90 | count
        i += 1
    for k in range(start, start + count):
        v = bits[k]
        out[i] = 0xCB
        for j in range(8):
            out[i + 8 - j] = (v >> np.uint64(8 * j)) & np.uint64(0xFF)
        i += 9
    return i


@hot_kernel
def encode_reply_into(out, reply_i, reply_f, tagged):
    """Write a REPLY into ``out`` (uint8 (≥ 327,)) from ``reply_i`` (int64 (REPLY_INTS,))
    and ``reply_f`` (float64 (REPLY_FLOATS,)): the bytes ``proto.codec.encode_reply_values``
    writes. With ``tagged`` the tag element is ``c4 10`` + 16 zero bytes, for the caller to
    fill with the MAC of everything before them; else nil. Returns the length, bytes."""
    bits = reply_f.view(np.uint64)
    out[0] = 0xDC  # array 16: a REPLY has 24 elements, more than a fixarray holds
    out[1] = 0
    out[2] = 24
    out[3] = VERSION
    out[4] = REPLY
    i = 5
    for k in range(R_BONE_VERSION):  # session … status
        i = _put_int(out, i, reply_i[k])
    for k in (R_FORCE, R_RESISTIVE, R_TORQUE):
        i = _put_floats(out, i, bits, k, 3, True)
    i = _put_floats(out, i, bits, R_POWER, 3, False)
    for k in (R_VIB_AXIS, R_PROXY_P, R_PROXY_V):
        i = _put_floats(out, i, bits, k, 3, True)
    i = _put_floats(out, i, bits, R_STIFFNESS, 3, False)
    i = _put_int(out, i, reply_i[R_BONE_VERSION])
    i = _put_floats(out, i, bits, R_FEED, 3, True)
    if tagged:
        out[i] = 0xC4
        out[i + 1] = 16
        for k in range(16):
            out[i + 2 + k] = 0
        return i + 18
    out[i] = 0xC0
    return i + 1


def warm_up() -> None:
    """Compile (or load from numba's cache) the kernels before serving."""
    rx, pose_i, pose_f, tx, reply_i = new_buffers()
    data = encode_pose(Pose(1, 2, 3, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, True))
    rx[:len(data)] = np.frombuffer(data, np.uint8)
    decode_pose_into(rx, len(data), pose_i, pose_f)
    reply_f = np.zeros(REPLY_FLOATS)
    encode_reply_into(tx, reply_i, reply_f, True)
