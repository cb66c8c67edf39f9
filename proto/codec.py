"""Encoding and decoding datagrams (SPEC.md). Decoders never raise anything but ProtocolError.

Encoders write the canonical form the golden vectors pin down: integers in msgpack's smallest
form, every float field as float64, vectors as arrays, the tag as bin 8. Decoders accept any
msgpack integer or float where a float is expected.
"""

from __future__ import annotations

import math

import msgpack

from .messages import (
    BAD_TYPE,
    BAD_VERSION,
    MALFORMED,
    MAX_REPLY_BYTES,
    MAX_REQUEST_BYTES,
    MAX_TIMESTAMP_US,
    NOTICE,
    NOTICE_FIELDS,
    POSE,
    POSE_FIELDS,
    REPLY,
    REPLY_FIELDS,
    SEQ_MODULUS,
    TAG_BYTES,
    TOO_BIG,
    VERSION,
    VERSION_1,
    Notice,
    Pose,
    Reply,
)
from .tag import Tagger

#: Limits for every msgpack object a peer sends: nothing in a valid message is bigger, and a
#: hostile datagram cannot make the decoder allocate much (it is at most MAX_*_BYTES anyway).
_LIMITS = {"max_str_len": 64, "max_bin_len": 64, "max_array_len": 32, "max_map_len": 16,
           "max_ext_len": 0}
_PLACEHOLDER = bytes(TAG_BYTES)
_unpackb = msgpack.unpackb
#: One packer for the process: packing is a single C call that holds the GIL.
_pack = msgpack.Packer().pack
#: Positions, ±engine units; speeds ±units/s; rpm ±: anything beyond is garbage, not a pose.
MAX_COORDINATE = 1e9
MAX_RPM = 1e7
#: A quaternion's norm must lie in this range (the server normalizes it).
QUATERNION_NORM_RANGE = (0.5, 1.5)
_UINT32 = SEQ_MODULUS


class ProtocolError(Exception):
    """A datagram that cannot be used.

    Attributes:
        code: the error code (``messages.ERROR_NAMES``).
        detail: what is wrong, for logs and tests.
        header: (session, seq, t_client_us) when the datagram's header could be read, else
            None (then no notice can be addressed).
        version: the datagram's version for BAD_VERSION (a v1 datagram is answered in v1's
            shape), else None.
    """

    def __init__(self, code: int, detail: str,
                 header: tuple[int, int, int] | None = None,
                 version: int | None = None) -> None:
        super().__init__(detail)
        self.code = code
        self.detail = detail
        self.header = header
        self.version = version


# -- helpers ------------------------------------------------------------------------------------
def _is_number(x: object) -> bool:
    t = type(x)
    return t is float or t is int


def _is_uint(x: object, bound: int) -> bool:
    return type(x) is int and 0 <= x < bound  # type: ignore[operator]


def _vec3(x: object) -> tuple[float, float, float] | None:
    """A msgpack array of 3 numbers as floats, or None."""
    if type(x) is not list or len(x) != 3:  # type: ignore[arg-type]
        return None
    a, b, c = x  # type: ignore[misc]
    if type(a) is float and type(b) is float and type(c) is float:
        return (a, b, c)
    if _is_number(a) and _is_number(b) and _is_number(c):
        return (float(a), float(b), float(c))
    return None


def _quat(x: object) -> tuple[float, float, float, float] | None:
    if type(x) is not list or len(x) != 4 or not all(  # type: ignore[arg-type]
            _is_number(v) for v in x):  # type: ignore[union-attr]
        return None
    a, b, c, d = x  # type: ignore[misc]
    return (float(a), float(b), float(c), float(d))


def _finite(values: tuple[float, ...], limit: float) -> bool:
    for x in values:
        if not -limit <= x <= limit:  # false for NaN too
            return False
    return True


def _unpack(data: bytes, limit: int) -> object:
    if len(data) > limit:
        raise ProtocolError(TOO_BIG, f"{len(data)} bytes, more than the {limit} allowed")
    try:
        return _unpackb(data, **_LIMITS)
    except Exception as exc:  # any msgpack failure: bad bytes, trailing data, limits
        raise ProtocolError(MALFORMED, f"not one msgpack object: {exc}") from None


def _header(msg: object) -> tuple[int, int, int, int, int]:
    """(version, type, session, seq, t_client_us), or MALFORMED without a header."""
    if type(msg) is not list or len(msg) < 5:  # type: ignore[arg-type]
        raise ProtocolError(MALFORMED, "not a msgpack array of at least 5 elements")
    version, kind, session, seq, t_client = msg[:5]  # type: ignore[index]
    if not (type(version) is int and type(kind) is int and _is_uint(session, _UINT32)
            and _is_uint(seq, _UINT32) and _is_uint(t_client, MAX_TIMESTAMP_US + 1)):
        raise ProtocolError(MALFORMED, "header must be [version, type, session (uint32), "
                                       "seq (uint32), t_client_us (uint63), ...]")
    return version, kind, session, seq, t_client


def _tag_field(value: object, header: tuple[int, int, int]) -> bytes | None:
    if value is None:
        return None
    if type(value) is bytes and len(value) == TAG_BYTES:
        return value
    raise ProtocolError(MALFORMED, "tag must be nil or a 16-byte bin", header)


def _pack_signed(fields: tuple, tagger: Tagger | None) -> bytes:
    """Pack ``fields`` + the tag element (the placeholder's bytes replaced by the tag)."""
    if tagger is None:
        return _pack((*fields, None))
    body = _pack((*fields, _PLACEHOLDER))[:-TAG_BYTES]
    return body + tagger.mac(body)


def _floats(v: object, n: int, name: str) -> tuple[float, ...]:
    out = tuple(x if type(x) is float else float(x) for x in v)  # type: ignore[union-attr]
    if len(out) != n:
        raise ValueError(f"{name} must have {n} numbers, got {len(out)}")
    return out


# -- POSE ---------------------------------------------------------------------------------------
def encode_pose(pose: Pose, tagger: Tagger | None = None) -> bytes:
    """The datagram of ``pose``, tagged with ``tagger``'s key (None: untagged). Ranges (ids,
    sequence numbers, stamps, flags) are the receiver's to check.

    Raises:
        ValueError: a vector of the wrong length.
        TypeError: a value that is not a number.
    """
    return _pack_signed(
        (VERSION, POSE, pose.session, pose.seq, pose.t_client_us,
         _floats(pose.position, 3, "position"), _floats(pose.orientation, 4, "orientation"),
         float(pose.rpm), bool(pose.spindle_on),
         None if pose.velocity is None else _floats(pose.velocity, 3, "velocity"),
         pose.flags, pose.stream), tagger)


def decode_pose(data: bytes) -> Pose:
    """Parse a POSE datagram. Checks shape and types only; :func:`check_pose_values` checks
    values (the server checks the tag in between).

    The common form (floats as floats, no velocity) is checked in one flat pass: on the hot
    loop a packet arrives after a millisecond asleep, with cold caches, where each Python
    call and object costs several times its warm price. Anything else takes the full path,
    which also says what is wrong.

    Raises:
        ProtocolError: TOO_BIG, MALFORMED, BAD_VERSION or BAD_TYPE.
    """
    if len(data) <= MAX_REQUEST_BYTES:
        try:
            msg = _unpackb(data, **_LIMITS)
        except Exception:
            msg = None
        if type(msg) is list and len(msg) == POSE_FIELDS:
            (version, kind, session, seq, t_client, p, q, rpm, on, velocity, flags, stream,
             tag) = msg
            if (type(version) is int and version == VERSION and type(kind) is int
                    and kind == POSE and type(session) is int and 0 <= session < _UINT32
                    and type(seq) is int and 0 <= seq < _UINT32 and type(t_client) is int
                    and 0 <= t_client <= MAX_TIMESTAMP_US and type(p) is list and len(p) == 3
                    and type(q) is list and len(q) == 4 and type(rpm) is float
                    and type(on) is bool and velocity is None and type(flags) is int
                    and 0 <= flags < _UINT32 and type(stream) is int and 0 <= stream < _UINT32
                    and (tag is None or (type(tag) is bytes and len(tag) == TAG_BYTES))):
                px, py, pz = p
                qx, qy, qz, qw = q
                if (type(px) is float and type(py) is float and type(pz) is float
                        and type(qx) is float and type(qy) is float and type(qz) is float
                        and type(qw) is float):
                    return Pose(session, seq, t_client, (px, py, pz), (qx, qy, qz, qw), rpm,
                                on, None, flags, stream, tag)
    return _decode_pose_checked(data)


def _decode_pose_checked(data: bytes) -> Pose:
    msg = _unpack(data, MAX_REQUEST_BYTES)
    version, kind, session, seq, t_client = _header(msg)
    header = (session, seq, t_client)
    if version != VERSION:
        raise ProtocolError(BAD_VERSION, f"version {version}; this server speaks {VERSION}",
                            header, version)
    if kind != POSE:
        raise ProtocolError(BAD_TYPE, f"message type {kind}; clients send {POSE} (POSE)",
                            header)
    if len(msg) != POSE_FIELDS:  # type: ignore[arg-type]
        raise ProtocolError(MALFORMED, f"a POSE has {POSE_FIELDS} elements, got "
                                       f"{len(msg)}", header)  # type: ignore[arg-type]
    (_, _, _, _, _, position, orientation, rpm, spindle_on, velocity, flags, stream,
     tag) = msg  # type: ignore[misc]
    position = _vec3(position)
    if position is None:
        raise ProtocolError(MALFORMED, "position must be an array of 3 numbers", header)
    orientation = _quat(orientation)
    if orientation is None:
        raise ProtocolError(MALFORMED, "orientation must be an array of 4 numbers (x, y, z, w)",
                            header)
    if not _is_number(rpm):
        raise ProtocolError(MALFORMED, "rpm must be a number", header)
    if type(spindle_on) is not bool:
        raise ProtocolError(MALFORMED, "spindle_on must be true or false", header)
    if velocity is not None:
        velocity = _vec3(velocity)
        if velocity is None:
            raise ProtocolError(MALFORMED, "velocity must be nil or an array of 3 numbers",
                                header)
    if not _is_uint(flags, _UINT32):
        raise ProtocolError(MALFORMED, "flags must be an unsigned 32-bit integer", header)
    if not _is_uint(stream, _UINT32):
        raise ProtocolError(MALFORMED, "stream must be an unsigned 32-bit integer", header)
    return Pose(session, seq, t_client, position, orientation, float(rpm), spindle_on,
                velocity, flags, stream, _tag_field(tag, header))


def check_pose_values(pose: Pose) -> str | None:
    """What is unusable about a well-formed pose's values, or None if nothing is."""
    if not _finite(pose.position, MAX_COORDINATE):
        return f"position must be finite and within ±{MAX_COORDINATE:g}"
    if not _finite(pose.orientation, MAX_COORDINATE):
        return "orientation must be finite"
    if pose.velocity is not None and not _finite(pose.velocity, MAX_COORDINATE):
        return f"velocity must be finite and within ±{MAX_COORDINATE:g}"
    if not -MAX_RPM <= pose.rpm <= MAX_RPM:
        return f"rpm must be finite and within ±{MAX_RPM:g}"
    x, y, z, w = pose.orientation
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    low, high = QUATERNION_NORM_RANGE
    if not low <= norm <= high:
        return f"orientation must be a unit quaternion (x, y, z, w); its norm is {norm:.3g}"
    return None


# -- REPLY and NOTICE ---------------------------------------------------------------------------
def encode_reply(reply: Reply, tagger: Tagger | None = None) -> bytes:
    """The datagram of ``reply`` (its own ``tag`` is ignored: ``tagger`` signs).

    Float fields should be floats (the server's are): an int is written as a msgpack int,
    which decoders accept but which is not the canonical form.
    """
    return _pack_signed((VERSION, REPLY, *reply[:-1]), tagger)


def encode_reply_values(values: tuple, tagger: Tagger | None = None) -> bytes:
    """:func:`encode_reply` from a plain tuple of the Reply's fields without the tag (the
    server's path: no NamedTuple built per packet)."""
    return _pack_signed((VERSION, REPLY, *values), tagger)


def encode_notice(notice: Notice, tagger: Tagger | None = None) -> bytes:
    return _pack_signed((VERSION, NOTICE, *notice[:-1]), tagger)


def encode_notice_values(session: int, seq: int, t_client_us: int, error: int, stream: int,
                         tagger: Tagger | None = None) -> bytes:
    """:func:`encode_notice` from plain values (the server's path: no NamedTuple per packet)."""
    return _pack_signed((VERSION, NOTICE, session, seq, t_client_us, error, stream), tagger)


def encode_bad_version_v1(session: int, seq: int, t_client_us: int) -> bytes:
    """The answer to a version-1 datagram: a BAD_VERSION notice in v1's own shape
    ``[1, 3, session, seq, t_client_us, 3, nil]``, so a v1 client can say "update me"."""
    return _pack((VERSION_1, NOTICE, session, seq, t_client_us, BAD_VERSION, None))


def decode_server_message(data: bytes) -> Reply | Notice:
    """Parse a REPLY or NOTICE (the client's side). Floats come back as Python floats.

    Raises:
        ProtocolError: anything that is not a well-formed REPLY or NOTICE of this version.
    """
    msg = _unpack(data, MAX_REPLY_BYTES)
    version, kind, session, seq, t_client = _header(msg)
    header = (session, seq, t_client)
    if version != VERSION:
        raise ProtocolError(BAD_VERSION, f"version {version}; this client speaks {VERSION}",
                            header, version)
    if kind == NOTICE:
        if (len(msg) != NOTICE_FIELDS or not _is_uint(msg[5], 1 << 16)  # type: ignore[arg-type,index]
                or not _is_uint(msg[6], _UINT32)):  # type: ignore[index]
            raise ProtocolError(MALFORMED, "a NOTICE is [2, 3, session, seq, t_client_us, "
                                           "error, stream, tag]", header)
        return Notice(session, seq, t_client, msg[5], msg[6],  # type: ignore[index]
                      _tag_field(msg[7], header))  # type: ignore[index]
    if kind != REPLY:
        raise ProtocolError(BAD_TYPE, f"message type {kind}; servers send 2 or 3", header)
    if len(msg) != REPLY_FIELDS:  # type: ignore[arg-type]
        raise ProtocolError(MALFORMED, f"a REPLY has {REPLY_FIELDS} elements", header)
    (_, _, _, _, _, t_recv, t_send, error, status, force, resistive, torque, power, amplitude,
     frequency, vib_axis, proxy_p, proxy_v, stiffness, damping, removed, bone_version,
     feed_v, tag) = msg  # type: ignore[misc]
    vectors = (_vec3(force), _vec3(resistive), _vec3(torque), _vec3(vib_axis), _vec3(proxy_p),
               _vec3(proxy_v), _vec3(feed_v))
    scalars = (power, amplitude, frequency, stiffness, damping, removed)
    if None in vectors or not all(_is_number(x) for x in scalars) or not (
            _is_uint(t_recv, 1 << 64) and _is_uint(t_send, 1 << 64)
            and _is_uint(error, 1 << 16) and _is_uint(status, 1 << 32)
            and _is_uint(bone_version, 1 << 64)):
        raise ProtocolError(MALFORMED, "a REPLY element has the wrong type", header)
    force, resistive, torque, vib_axis, proxy_p, proxy_v, feed_v = vectors
    return Reply(session, seq, t_client, t_recv, t_send, error, status, force, resistive,
                 torque, float(power), float(amplitude), float(frequency), vib_axis, proxy_p,
                 proxy_v, float(stiffness), float(damping), float(removed), bone_version,
                 feed_v, _tag_field(tag, header))  # type: ignore[arg-type]


def read_header(data: bytes) -> tuple[int, int, int, int, int] | None:
    """(version, type, session, seq, t_client_us) of any datagram, or None (for tools and
    logs: which session and packet a datagram claims to be)."""
    try:
        return _header(_unpack(data, max(MAX_REQUEST_BYTES, MAX_REPLY_BYTES)))
    except ProtocolError:
        return None
