"""The wire protocol's messages, field by field (SPEC.md is the normative description).

Every datagram is one msgpack array. Elements 0–4 mean the same in every message type and every
protocol version (version, type, session, sequence, client timestamp), so a receiver can always
say which session and packet an error is about.
"""

from __future__ import annotations

from typing import NamedTuple

#: Protocol version this codec speaks.
VERSION = 2
#: The previous version: only ever answered with a BAD_VERSION notice in its own shape.
VERSION_1 = 1

# Message types (element 1).
POSE = 1  #: client → server: the burr's pose and spindle state.
REPLY = 2  #: server → client: the force and everything else of one tick.
NOTICE = 3  #: server → client: a short error notice (the request was not processed).

# Request flags (bit mask, element 10 of a POSE). Receivers ignore bits they do not know.
# Bit 2 (v1's FLAG_NEW_STREAM) is reserved again: streams are handed out by the server.
FLAG_RESET_VELOCITY = 1  #: do not estimate velocity from the previous pose (a teleport).
FLAG_NO_CARVE = 2  #: evaluate the force but remove no bone.

#: A POSE whose stream (element 11) is this asks for a stream ("hello"); it is not ticked.
HELLO_STREAM = 0

# Reply status flags (bit mask).
STATUS_CUTTING = 1  #: the burr removes bone this tick (spindle at cutting speed, feeding in).
STATUS_CONTACT = 2  #: part of the burr lies in bone.
STATUS_FORBIDDEN = 4  #: the burr overlaps a forbidden structure (a nerve, say).
STATUS_CLAMPED = 8  #: an output was limited (force or speed limits).
STATUS_STALE = 16  #: no velocity estimate this tick (first packet, gap, reset): feed taken as 0.
STATUS_SHAFT_CONTACT = 32  #: the shaft touches bone.
STATUS_SLOW_SPINDLE = 64  #: spindle on but below the minimum cutting speed: touching, not cutting.

STATUS_NAMES = {
    STATUS_CUTTING: "cutting",
    STATUS_CONTACT: "contact",
    STATUS_FORBIDDEN: "forbidden",
    STATUS_CLAMPED: "clamped",
    STATUS_STALE: "stale",
    STATUS_SHAFT_CONTACT: "shaft_contact",
    STATUS_SLOW_SPINDLE: "slow_spindle",
}

# Error codes (REPLY element 7, NOTICE element 5).
OK = 0
MALFORMED = 1  #: not a msgpack array of the request's shape, or a field of the wrong type.
TOO_BIG = 2  #: datagram longer than MAX_REQUEST_BYTES.
BAD_VERSION = 3  #: a protocol version this server does not speak.
BAD_TYPE = 4  #: a message type a client may not send.
UNKNOWN_SESSION = 5  #: no such session.
BAD_TAG = 6  #: the tag is missing or wrong (wrong key, or the bytes were altered).
BAD_VALUE = 7  #: well-formed and authentic, but a value is unusable (NaN, zero quaternion, …).
STALE = 8  #: older than a packet already accepted (never answered).
DUPLICATE = 9  #: the same sequence number again (never answered).
INTERNAL = 10  #: the server failed on this packet (a bug: please report it).
#: (notice) a stream is open for you: put the notice's stream in element 11 of your POSEs.
NEW_STREAM = 11
#: (notice) the POSE's stream is not (or no longer) open: send a hello (stream 0).
WRONG_STREAM = 12

ERROR_NAMES = {
    OK: "ok",
    MALFORMED: "malformed",
    TOO_BIG: "too_big",
    BAD_VERSION: "bad_version",
    BAD_TYPE: "bad_type",
    UNKNOWN_SESSION: "unknown_session",
    BAD_TAG: "bad_tag",
    BAD_VALUE: "bad_value",
    STALE: "stale",
    DUPLICATE: "duplicate",
    INTERNAL: "internal",
    NEW_STREAM: "new_stream",
    WRONG_STREAM: "wrong_stream",
}

#: Requests longer than this are dropped unread (a POSE is ~115 bytes).
MAX_REQUEST_BYTES = 512
#: Replies are at most this long (a REPLY is ~300 bytes): a receive buffer this size is enough.
MAX_REPLY_BYTES = 1024
#: Bytes of the truncated HMAC-SHA256 tag.
TAG_BYTES = 16
#: Sequence numbers are unsigned 32-bit and wrap around.
SEQ_MODULUS = 1 << 32
#: Largest client timestamp, µs (signed 64-bit range, so every language can hold it).
MAX_TIMESTAMP_US = (1 << 63) - 1

# Element counts (the tag included).
POSE_FIELDS = 13
REPLY_FIELDS = 24
NOTICE_FIELDS = 8
#: A v1 NOTICE (the BAD_VERSION answer to a v1 datagram): [1, 3, session, seq, t, error, tag].
NOTICE_V1_FIELDS = 7


class Pose(NamedTuple):
    """A POSE request (client → server). Units and axes are the session's engine frame.

    Attributes:
        session: session id (unsigned 32-bit).
        seq: sequence number (unsigned 32-bit, wraps).
        t_client_us: the client's monotonic clock, µs.
        position: burr centre (x, y, z), engine length unit.
        orientation: tool orientation quaternion (x, y, z, w), engine frame; the session's
            tool axis (a local axis) is rotated by it.
        rpm: spindle speed, rpm; the sign is the direction (+ = the session's forward spin).
        spindle_on: the spindle runs.
        velocity: the burr centre's velocity (x, y, z), engine length unit per second, or None
            to let the server estimate it from positions and client timestamps.
        flags: FLAG_* bits.
        stream: the stream number the server gave this client (unsigned 32-bit), or
            HELLO_STREAM (0) to ask for one (the pose is then not ticked).
        tag: the 16-byte tag, or None for a session without a key.
    """

    session: int
    seq: int
    t_client_us: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    rpm: float
    spindle_on: bool
    velocity: tuple[float, float, float] | None = None
    flags: int = 0
    stream: int = HELLO_STREAM
    tag: bytes | None = None


class Reply(NamedTuple):
    """A REPLY (server → client): one tick. Vectors are on the engine's axes; "L" is the
    engine's length unit (mm, m or cm).

    Attributes:
        session, seq, t_client_us: echoed from the request.
        t_recv_us, t_send_us: the server's monotonic clock when the datagram arrived and just
            before the reply was encoded, µs.
        error: OK, BAD_VALUE or INTERNAL. With an error every force, torque, vibration and
            coupling field is zero: render nothing from it.
        status: STATUS_* bits.
        force: what the hand should feel, N (force of the bone on the tool: cutting + shaft).
        resistive: the cutting force's (feed, lateral, normal) components, N (model.md).
        torque: reaction torque on the burr about its centre, N·L.
        power_w: spindle power spent cutting, W.
        vibration_amplitude: N; vibration_frequency_hz: Hz; vibration_axis: a unit vector.
        proxy_position (L), proxy_velocity (L/s), coupling_stiffness (N/L),
            coupling_damping (N·s/L): the coupling model (zero: no coupling model).
        removed_mm3: bone removed this tick, mm³ (in every frame).
        bone_version: the bone's version after this tick.
        feed_velocity: the burr velocity the model used, L/s.
        tag: the tag, or None (session without a key).
    """

    session: int
    seq: int
    t_client_us: int
    t_recv_us: int
    t_send_us: int
    error: int
    status: int
    force: tuple[float, float, float]
    resistive: tuple[float, float, float]
    torque: tuple[float, float, float]
    power_w: float
    vibration_amplitude: float
    vibration_frequency_hz: float
    vibration_axis: tuple[float, float, float]
    proxy_position: tuple[float, float, float]
    proxy_velocity: tuple[float, float, float]
    coupling_stiffness: float
    coupling_damping: float
    removed_mm3: float
    bone_version: int
    feed_velocity: tuple[float, float, float]
    tag: bytes | None = None

    def status_names(self) -> list[str]:
        return [name for bit, name in STATUS_NAMES.items() if self.status & bit]


class Notice(NamedTuple):
    """A NOTICE (server → client): the request was not processed.

    Attributes:
        session, seq, t_client_us: echoed from the request.
        error: an error code (``ERROR_NAMES``).
        stream: for NEW_STREAM the stream the client is to use; for WRONG_STREAM the stream
            the refused POSE carried; 0 in every other notice.
        tag: tagged with the session's key for BAD_TAG, NEW_STREAM and WRONG_STREAM notices
            (the session is known; None for a session without a key); None for notices sent
            before a session was identified (malformed, wrong version or type, unknown
            session).
    """

    session: int
    seq: int
    t_client_us: int
    error: int
    stream: int = 0
    tag: bytes | None = None

    @property
    def error_name(self) -> str:
        return ERROR_NAMES.get(self.error, f"error {self.error}")
