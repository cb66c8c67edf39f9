"""The wire protocol's codec: golden vectors, tags, round trips, errors, fuzz, sequence numbers."""

from __future__ import annotations

import hashlib
import hmac
import importlib.util
import json
import math
import struct
from pathlib import Path

import msgpack
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from burrforce.proto import codec
from burrforce.proto.codec import (
    ProtocolError,
    check_pose_values,
    decode_pose,
    decode_server_message,
    encode_bad_version_v1,
    encode_notice,
    encode_notice_values,
    encode_pose,
    encode_reply,
    read_header,
)
from burrforce.proto.messages import (
    BAD_TAG,
    BAD_TYPE,
    BAD_VERSION,
    MALFORMED,
    MAX_REPLY_BYTES,
    MAX_REQUEST_BYTES,
    MAX_TIMESTAMP_US,
    NEW_STREAM,
    NOTICE,
    POSE,
    REPLY,
    TAG_BYTES,
    TOO_BIG,
    VERSION,
    VERSION_1,
    WRONG_STREAM,
    Notice,
    Pose,
    Reply,
)
from burrforce.proto.sequence import seq_after, seq_next
from burrforce.proto.tag import KEY_BYTES, TAG_HEADER, Tagger, new_key, parse_key

VECTORS_DIR = Path(__file__).resolve().parents[1] / "proto" / "vectors"
VECTORS = json.loads((VECTORS_DIR / "vectors.json").read_text(encoding="utf-8"))
KEY = bytes.fromhex("00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff")
CLASSES = {"pose": Pose, "reply": Reply, "notice": Notice}
TYPE_CODES = {"pose": POSE, "reply": REPLY, "notice": NOTICE}
U32 = 1 << 32


# -- helpers ------------------------------------------------------------------------------------
def canon(x: object) -> object:
    """``x`` with every float replaced by its float64 bits and every leaf tagged with its type:
    equal canon means bit-identical values of identical types (-0.0 ≠ 0.0, NaN = same NaN,
    True ≠ 1, 1.0 ≠ 1, tuple and list alike)."""
    if isinstance(x, (list, tuple)):
        return ("seq", [canon(v) for v in x])
    if type(x) is float:
        return ("float", struct.pack(">d", x))
    return (type(x).__name__, x)


def wire_fields(vec: dict) -> list[str]:
    """The field names of ``vec``'s message in wire order (a v1 NOTICE has no stream)."""
    names = [f for f in CLASSES[vec["type"]]._fields if f != "tag"]
    return [f for f in names if f != "stream"] if vec["version"] == VERSION_1 else names


def message_from_fields(kind: str, fields: dict) -> Pose | Reply | Notice:
    cls = CLASSES[kind]
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})


V2_VECTORS = [v for v in VECTORS if v["version"] == VERSION]


def encode_any(message: Pose | Reply | Notice, tagger: Tagger | None) -> bytes:
    if isinstance(message, Pose):
        return encode_pose(message, tagger)
    if isinstance(message, Reply):
        return encode_reply(message, tagger)
    return encode_notice(message, tagger)


def decode_any(kind: str, data: bytes) -> Pose | Reply | Notice:
    return decode_pose(data) if kind == "pose" else decode_server_message(data)


def truncated_hmac(key: bytes, data: bytes) -> bytes:
    return hmac.new(key, data, hashlib.sha256).digest()[:16]


def vector_id(v: dict) -> str:
    return v["name"]


# -- golden vectors -----------------------------------------------------------------------------
def test_vectors_cover_the_required_cases():
    names = [v["name"] for v in VECTORS]
    assert len(names) == len(set(names)) >= 11
    assert {"pose_hello", "notice_new_stream", "notice_wrong_stream",
            "notice_bad_version_v1"} <= set(names)
    assert {v["version"] for v in VECTORS} == {VERSION, VERSION_1}
    assert [v["name"] for v in VECTORS if v["version"] == VERSION_1] == ["notice_bad_version_v1"]
    assert {v["type"] for v in VECTORS} == {"pose", "reply", "notice"}
    for kind in ("pose", "reply", "notice"):
        of_kind = [v for v in VECTORS if v["type"] == kind]
        assert any(v["key_hex"] for v in of_kind) and any(v["key_hex"] is None for v in of_kind)
    for v in VECTORS:
        assert v["key_hex"] in (None, KEY.hex())
        assert v["hex"] == v["hex"].lower() and v["description"].strip()
        assert "tag" not in v["fields"]
        assert list(v["fields"]) == wire_fields(v), "fields in wire order"
        if v["type"] == "pose" and v["name"] != "pose_hello":
            assert v["fields"]["stream"] != 0, "POSE vectors carry a stream"


def test_vectors_follow_the_spec_rules():
    """An error REPLY has status 0 and every float zero; only the notices about a known
    session (BAD_TAG, NEW_STREAM, WRONG_STREAM) are tagged; only those two carry a stream."""
    for v in VECTORS:
        fields = v["fields"]
        if v["type"] == "reply" and fields["error"] != 0:
            assert fields["status"] == 0
            for name, value in fields.items():
                if isinstance(value, (float, list)):
                    assert value in (0.0, [0.0, 0.0, 0.0]), name
        if v["type"] == "notice":
            known = (BAD_TAG, NEW_STREAM, WRONG_STREAM)
            assert (v["key_hex"] is not None) == (fields["error"] in known)
            assert (fields.get("stream", 0) != 0) == (fields["error"] in known[1:])


def test_the_handshake_vectors_follow_the_client_rule():
    """SPEC 5.2's client rule on the vectors: having sent pose_hello, a client ignores
    notice_new_stream_replayed (its seq, not its t_client_us) and takes notice_new_stream
    (both); then notice_wrong_stream, about the stream it took, sends it back to hello."""
    from burrforce.client.udp import SessionRules

    v = {vec["name"]: vec for vec in VECTORS}
    hello = v["pose_hello"]["fields"]
    rules = SessionRules(hello["session"], KEY, hello["seq"])
    _, sent = rules.datagram(hello["position"], hello["orientation"], hello["rpm"],
                             hello["spindle_on"], hello["velocity"], hello["flags"],
                             hello["t_client_us"])
    assert sent.hex() == v["pose_hello"]["hex"]
    replayed = rules.accept(bytes.fromhex(v["notice_new_stream_replayed"]["hex"]), 0)
    assert replayed.error == NEW_STREAM and rules.stream == 0  # authentic, and ignored
    rules.accept(bytes.fromhex(v["notice_new_stream"]["hex"]), 0)
    assert rules.stream == v["notice_new_stream"]["fields"]["stream"]
    rules.accept(bytes.fromhex(v["notice_wrong_stream"]["hex"]), 0)
    assert rules.stream == 0 and rules.counters["wrong_stream"] == 1


@pytest.mark.parametrize("vec", V2_VECTORS, ids=vector_id)
def test_vector_encodes_to_its_bytes(vec):
    message = message_from_fields(vec["type"], vec["fields"])
    tagger = Tagger(bytes.fromhex(vec["key_hex"])) if vec["key_hex"] else None
    assert encode_any(message, tagger).hex() == vec["hex"]


def test_v1_bad_version_vector():
    """The one v1 vector: what a v2 server answers a v1 datagram with; a v2 client's decoder
    refuses it as BAD_VERSION, with its header."""
    (vec,) = [v for v in VECTORS if v["version"] == VERSION_1]
    f = vec["fields"]
    data = bytes.fromhex(vec["hex"])
    assert encode_bad_version_v1(f["session"], f["seq"], f["t_client_us"]) == data
    assert msgpack.unpackb(data) == [1, NOTICE, f["session"], f["seq"], f["t_client_us"],
                                     BAD_VERSION, None]
    err = _error(data, decode_server_message)
    assert (err.code, err.header) == (BAD_VERSION, (f["session"], f["seq"], f["t_client_us"]))


@pytest.mark.parametrize("vec", VECTORS, ids=vector_id)
def test_vector_bytes_are_the_canonical_msgpack(vec):
    """The bytes, rebuilt with plain msgpack and hmac (no burrforce code): the canonical form is
    msgpack's default packing (smallest ints, float64 floats, bin for bytes), tag last."""
    values = [vec["fields"][f] for f in wire_fields(vec)]
    elements = [vec["version"], TYPE_CODES[vec["type"]], *values]
    if vec["key_hex"] is None:
        expected = msgpack.packb([*elements, None])
    else:
        body = msgpack.packb([*elements, bytes(TAG_BYTES)])[:-TAG_BYTES]
        expected = body + truncated_hmac(bytes.fromhex(vec["key_hex"]), body)
    assert expected.hex() == vec["hex"]
    assert len(expected) <= (MAX_REQUEST_BYTES if vec["type"] == "pose" else MAX_REPLY_BYTES)


@pytest.mark.parametrize("vec", V2_VECTORS, ids=vector_id)
def test_vector_decodes_to_its_fields(vec):
    data = bytes.fromhex(vec["hex"])
    decoded = decode_any(vec["type"], data)
    assert type(decoded) is CLASSES[vec["type"]]
    got = {k: v for k, v in decoded._asdict().items() if k != "tag"}
    assert list(got) == list(vec["fields"])
    for name, value in got.items():
        assert canon(value) == canon(vec["fields"][name]), name
    assert decoded.tag == (data[-TAG_BYTES:] if vec["key_hex"] else None)


@pytest.mark.parametrize("vec", VECTORS, ids=vector_id)
def test_vector_tag(vec):
    data = bytes.fromhex(vec["hex"])
    if vec["key_hex"] is None:
        assert data[-1:] == b"\xc0"  # nil: no tag
        assert not Tagger(KEY).verify(data)
        return
    key = bytes.fromhex(vec["key_hex"])
    assert data[-TAG_BYTES - 2:-TAG_BYTES] == TAG_HEADER
    assert data[-TAG_BYTES:] == truncated_hmac(key, data[:-TAG_BYTES])
    assert Tagger(key).verify(data)
    for other in (bytes(32), key[:-1], key[::-1], key[:-1] + b"\xfe", b"\x01"):
        assert not Tagger(other).verify(data)
    n = len(data)
    positions = sorted({0, 1, 2, 5, n // 2, n - 19, n - 18, n - 17, n - 16, n - 9, n - 1})
    for i in positions:
        for mask in (0x01, 0x80, 0xFF):
            altered = bytearray(data)
            altered[i] ^= mask
            assert not Tagger(key).verify(bytes(altered)), (i, mask)
    assert not Tagger(key).verify(data[:-1])
    assert not Tagger(key).verify(data + b"\x00")


def _load_make_vectors():
    spec = importlib.util.spec_from_file_location("make_vectors", VECTORS_DIR / "make_vectors.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_make_vectors_reproduces_the_file():
    """vectors.json is exactly what make_vectors.py writes (no hand edits, no drift)."""
    make_vectors = _load_make_vectors()
    assert make_vectors.KEY_HEX == KEY.hex()
    text = (VECTORS_DIR / "vectors.json").read_text(encoding="utf-8")
    assert make_vectors.dumps(make_vectors.build()) == text


# -- tags ---------------------------------------------------------------------------------------
keys = st.binary(min_size=1, max_size=200)


@given(key=keys, data=st.binary(max_size=600))
def test_tagger_mac_is_truncated_hmac_sha256(key, data):
    assert Tagger(key).mac(data) == truncated_hmac(key, data)
    assert Tagger(bytearray(key)).mac(memoryview(data)) == truncated_hmac(key, data)


@pytest.mark.parametrize("length", [1, 31, 32, 63, 64, 65, 128, 300])
def test_tagger_key_lengths_around_the_block_size(length):
    key = bytes((7 * i + 3) % 256 for i in range(length))
    data = b"burrforce" * 20
    assert Tagger(key).mac(data) == truncated_hmac(key, data)


@pytest.mark.parametrize("key", [b"", "00ff", None])
def test_tagger_rejects_empty_or_non_bytes_keys(key):
    with pytest.raises(ValueError):
        Tagger(key)


def test_keys_and_their_hex_form():
    key = new_key()
    assert type(key) is bytes and len(key) == KEY_BYTES and key != new_key()
    assert parse_key(key.hex()) == key
    assert parse_key(f"  {KEY.hex().upper()}\n") == KEY
    for bad in ("", "   ", "0", "zz", "00 11 2"):
        with pytest.raises(ValueError):
            parse_key(bad)


@given(key=keys, seq=st.integers(0, U32 - 1), error=st.integers(0, 10))
def test_encoded_tag_is_hmac_of_everything_before_it(key, seq, error):
    tagger = Tagger(key)
    pose = Pose(1, seq, 5, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 100.0, True)
    for data in (encode_pose(pose, tagger), encode_notice(Notice(1, seq, 5, error), tagger)):
        assert data[-TAG_BYTES - 2:-TAG_BYTES] == TAG_HEADER
        assert data[-TAG_BYTES:] == truncated_hmac(key, data[:-TAG_BYTES])
        assert tagger.verify(data)
        placeholder = bytearray(data[:-TAG_BYTES] + bytes(TAG_BYTES))
        tagger.sign(placeholder)
        assert bytes(placeholder) == data


# -- round trips --------------------------------------------------------------------------------
finite = st.floats(allow_nan=False, allow_infinity=False)
any_float = st.floats()
uint32 = st.integers(0, U32 - 1)
uint64 = st.integers(0, (1 << 64) - 1)
timestamps = st.integers(0, MAX_TIMESTAMP_US)
keys_or_none = st.none() | st.binary(min_size=1, max_size=100)  # a key, or untagged


def vec3(f=finite):
    return st.tuples(f, f, f)


def poses(f=finite):
    return st.builds(Pose, session=uint32, seq=uint32, t_client_us=timestamps,
                     position=vec3(f), orientation=st.tuples(f, f, f, f), rpm=f,
                     spindle_on=st.booleans(), velocity=st.none() | vec3(f), flags=uint32,
                     stream=uint32)


def replies(f=finite):
    return st.builds(Reply, session=uint32, seq=uint32, t_client_us=timestamps,
                     t_recv_us=uint64, t_send_us=uint64, error=st.integers(0, 0xFFFF),
                     status=uint32, force=vec3(f), resistive=vec3(f), torque=vec3(f),
                     power_w=f, vibration_amplitude=f, vibration_frequency_hz=f,
                     vibration_axis=vec3(f), proxy_position=vec3(f), proxy_velocity=vec3(f),
                     coupling_stiffness=f, coupling_damping=f, removed_mm3=f,
                     bone_version=uint64, feed_velocity=vec3(f))


notices = st.builds(Notice, session=uint32, seq=uint32, t_client_us=timestamps,
                    error=st.integers(0, 0xFFFF), stream=uint32)


def _check_round_trip(message, key, decode):
    tagger = Tagger(key) if key is not None else None
    data = encode_any(message, tagger)
    decoded = decode(data)
    assert type(decoded) is type(message)
    expected_tag = data[-TAG_BYTES:] if key is not None else None
    assert canon(decoded) == canon(message._replace(tag=expected_tag))
    if key is not None:
        assert tagger.verify(data)
    return data


@given(pose=poses(), key=keys_or_none)
def test_pose_round_trip(pose, key):
    data = _check_round_trip(pose, key, decode_pose)
    assert len(data) <= MAX_REQUEST_BYTES


@given(pose=poses(any_float), key=keys_or_none)
def test_pose_round_trip_is_bit_exact_for_any_float64(pose, key):
    """Decoding checks shape, not values: NaN, ±inf and -0.0 come back bit for bit."""
    _check_round_trip(pose, key, decode_pose)


@given(reply=replies(), key=keys_or_none)
def test_reply_round_trip(reply, key):
    data = _check_round_trip(reply, key, decode_server_message)
    assert len(data) <= MAX_REPLY_BYTES


@given(reply=replies(any_float), key=keys_or_none)
def test_reply_round_trip_is_bit_exact_for_any_float64(reply, key):
    _check_round_trip(reply, key, decode_server_message)


@given(notice=notices, key=keys_or_none)
def test_notice_round_trip(notice, key):
    _check_round_trip(notice, key, decode_server_message)


@given(session=uint32, seq=uint32, t=timestamps, error=st.integers(0, 0xFFFF), stream=uint32,
       key=keys_or_none)
def test_encode_notice_values_matches_encode_notice(session, seq, t, error, stream, key):
    tagger = Tagger(key) if key is not None else None
    assert (encode_notice_values(session, seq, t, error, stream, tagger)
            == encode_notice(Notice(session, seq, t, error, stream), tagger))


@given(pose=poses(any_float).map(lambda p: p._replace(velocity=None)), tagged=st.booleans())
def test_fast_and_full_pose_paths_agree(pose, tagged):
    """decode_pose's flat fast path returns exactly what the checked path returns."""
    data = encode_pose(pose, Tagger(KEY) if tagged else None)
    assert canon(decode_pose(data)) == canon(codec._decode_pose_checked(data))


def test_encode_pose_rejects_vectors_of_the_wrong_length():
    pose = Pose(1, 1, 1, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False)
    for bad in (pose._replace(position=(0.0, 0.0)), pose._replace(orientation=(0.0, 0.0, 1.0)),
                pose._replace(velocity=(1.0, 2.0, 3.0, 4.0))):
        with pytest.raises(ValueError):
            encode_pose(bad)


def test_encode_pose_writes_canonical_floats_from_ints():
    """Ints given for floats are written as float64, so the bytes equal the float version."""
    as_ints = Pose(1, 1, 1, (1, 2, 3), (0, 0, 0, 1), 60000, 1, (4, 5, 6))
    as_floats = Pose(1, 1, 1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 60000.0, True,
                     (4.0, 5.0, 6.0))
    assert encode_pose(as_ints) == encode_pose(as_floats)
    assert canon(decode_pose(encode_pose(as_ints))) == canon(as_floats)


# -- non-canonical msgpack ----------------------------------------------------------------------
# A tiny msgpack writer with a choice of form for every element (all valid msgpack).
def _int_forms(n: int) -> list[str]:
    forms = []
    if 0 <= n < 128 or -32 <= n < 0:
        forms.append("fix")
    if n >= 0:
        forms += [f for f, bits in (("u8", 8), ("u16", 16), ("u32", 32), ("u64", 64))
                  if n < 1 << bits]
    forms += [f for f, bits in (("i8", 8), ("i16", 16), ("i32", 32), ("i64", 64))
              if -(1 << (bits - 1)) <= n < 1 << (bits - 1)]
    return forms


_INT_CODES = {"u8": (0xCC, ">B"), "u16": (0xCD, ">H"), "u32": (0xCE, ">I"), "u64": (0xCF, ">Q"),
              "i8": (0xD0, ">b"), "i16": (0xD1, ">h"), "i32": (0xD2, ">i"), "i64": (0xD3, ">q")}


def _pack_int(n: int, form: str) -> bytes:
    if form == "fix":
        return bytes([n & 0xFF])
    code, fmt = _INT_CODES[form]
    return bytes([code]) + struct.pack(fmt, n)


def _float32_exact(x: float) -> bool:
    try:
        return struct.unpack(">f", struct.pack(">f", x))[0] == x
    except OverflowError:
        return False


def _float_forms(x: float) -> list[str]:
    forms = ["f64"]
    if _float32_exact(x):
        forms.append("f32")
    negative_zero = x == 0.0 and math.copysign(1.0, x) < 0
    if x.is_integer() and not negative_zero and -(1 << 63) <= x < 1 << 64:
        forms.append("int")
    return forms


def _array_header(n: int, form: str) -> bytes:
    if form == "fix":
        return bytes([0x90 | n])
    if form == "a16":
        return b"\xdc" + struct.pack(">H", n)
    return b"\xdd" + struct.pack(">I", n)


def _draw_int(data, n: int) -> bytes:
    return _pack_int(n, data.draw(st.sampled_from(_int_forms(n))))


def _draw_float(data, x: float) -> bytes:
    form = data.draw(st.sampled_from(_float_forms(x)))
    if form == "f64":
        return b"\xcb" + struct.pack(">d", x)
    if form == "f32":
        return b"\xca" + struct.pack(">f", x)
    n = int(x)
    return _draw_int(data, n)


def _draw_array(data, parts: list[bytes]) -> bytes:
    form = data.draw(st.sampled_from(["fix", "a16", "a32"] if len(parts) < 16 else ["a16", "a32"]))
    return _array_header(len(parts), form) + b"".join(parts)


def _draw_vec(data, v) -> bytes:
    return _draw_array(data, [_draw_float(data, x) for x in v])


def _draw_tag(data, tag: bytes | None) -> bytes:
    if tag is None:
        return b"\xc0"
    form = data.draw(st.sampled_from(["b8", "b16", "b32"]))
    header = {"b8": b"\xc4" + bytes([len(tag)]), "b16": b"\xc5" + struct.pack(">H", len(tag)),
              "b32": b"\xc6" + struct.pack(">I", len(tag))}[form]
    return header + tag


def _draw_header(data, kind: int, m) -> list[bytes]:
    return [_draw_int(data, VERSION), _draw_int(data, kind), _draw_int(data, m.session),
            _draw_int(data, m.seq), _draw_int(data, m.t_client_us)]


# Floats that often have an int or float32 form.
friendly = st.one_of(st.integers(-(10**6), 10**6).map(float), st.floats(width=32,
                     allow_nan=False, allow_infinity=False), finite)
tags = st.none() | st.binary(min_size=TAG_BYTES, max_size=TAG_BYTES)


@given(pose=poses(friendly), tag=tags, data=st.data())
def test_decode_pose_accepts_non_canonical_msgpack(pose, tag, data):
    parts = [*_draw_header(data, POSE, pose), _draw_vec(data, pose.position),
             _draw_vec(data, pose.orientation), _draw_float(data, pose.rpm),
             b"\xc3" if pose.spindle_on else b"\xc2",
             b"\xc0" if pose.velocity is None else _draw_vec(data, pose.velocity),
             _draw_int(data, pose.flags), _draw_int(data, pose.stream), _draw_tag(data, tag)]
    datagram = _draw_array(data, parts)
    assume(len(datagram) <= MAX_REQUEST_BYTES)
    decoded = decode_pose(datagram)
    assert canon(decoded) == canon(pose._replace(tag=tag))


@given(reply=replies(friendly), tag=tags, data=st.data())
def test_decode_reply_accepts_non_canonical_msgpack(reply, tag, data):
    parts = _draw_header(data, REPLY, reply)
    for name in Reply._fields[3:-1]:
        value = getattr(reply, name)
        if isinstance(value, tuple):
            parts.append(_draw_vec(data, value))
        elif isinstance(value, int):
            parts.append(_draw_int(data, value))
        else:
            parts.append(_draw_float(data, value))
    parts.append(_draw_tag(data, tag))
    datagram = _draw_array(data, parts)
    assume(len(datagram) <= MAX_REPLY_BYTES)
    assert canon(decode_server_message(datagram)) == canon(reply._replace(tag=tag))


@given(notice=notices, tag=tags, data=st.data())
def test_decode_notice_accepts_non_canonical_msgpack(notice, tag, data):
    datagram = _draw_array(data, [*_draw_header(data, NOTICE, notice),
                                  _draw_int(data, notice.error), _draw_int(data, notice.stream),
                                  _draw_tag(data, tag)])
    assert canon(decode_server_message(datagram)) == canon(notice._replace(tag=tag))


def test_decode_pose_accepts_single_floats_and_ints_via_msgpack():
    elements = [2, 1, 70000, 300, 1 << 40, [1, -2, 3], [0, 0, 0, 1], 60000, True, [0.5, 1, -2],
                6, 9, None]
    pose = decode_pose(msgpack.packb(elements))
    assert canon(pose) == canon(Pose(70000, 300, 1 << 40, (1.0, -2.0, 3.0), (0.0, 0.0, 0.0, 1.0),
                                     60000.0, True, (0.5, 1.0, -2.0), 6, 9, None))
    elements[5:8] = [[0.1, 0.2, 0.3], [0.0, 0.0, 0.6, 0.8], 1234.5]
    single = msgpack.packb(elements, use_single_float=True)
    assert single.count(b"\xca") == 9 and b"\xcb" not in single
    pose = decode_pose(single)
    f32 = [struct.unpack(">f", struct.pack(">f", x))[0] for x in (0.1, 0.2, 0.3, 0.6, 0.8)]
    assert pose.position == (f32[0], f32[1], f32[2])
    assert pose.orientation == (0.0, 0.0, f32[3], f32[4])
    assert pose.rpm == 1234.5 and type(pose.rpm) is float
    assert all(type(x) is float for x in (*pose.position, *pose.orientation, *pose.velocity))


# -- decode_pose errors -------------------------------------------------------------------------
HEADER = (7, 3, 1000)
VALID = [2, 1, *HEADER, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], 60000.0, True, None, 0, 77,
         None]


def _with(index: int, value: object) -> list:
    out = list(VALID)
    out[index] = value
    return out


def _error(data: bytes, decode=decode_pose) -> ProtocolError:
    with pytest.raises(ProtocolError) as info:
        decode(data)
    return info.value


def test_valid_base_datagram_decodes():
    assert decode_pose(msgpack.packb(VALID)) == Pose(7, 3, 1000, (1.0, 2.0, 3.0),
                                                     (0.0, 0.0, 0.0, 1.0), 60000.0, True,
                                                     stream=77)


def test_limits_of_header_fields_are_accepted():
    data = msgpack.packb([2, 1, U32 - 1, U32 - 1, MAX_TIMESTAMP_US, *VALID[5:]])
    assert decode_pose(data)[:3] == (U32 - 1, U32 - 1, MAX_TIMESTAMP_US)
    assert decode_pose(msgpack.packb(_with(10, U32 - 1))).flags == U32 - 1
    assert decode_pose(msgpack.packb(_with(11, U32 - 1))).stream == U32 - 1
    assert decode_pose(msgpack.packb(_with(11, 0))).stream == 0


def test_too_big():
    for data in (bytes(MAX_REQUEST_BYTES + 1), msgpack.packb(VALID).ljust(513, b"\xc0"),
                 b"\x00" * 10_000):
        err = _error(data)
        assert (err.code, err.header) == (TOO_BIG, None)


def test_exactly_max_request_bytes_is_read():
    """512 bytes are read (and here found malformed, with a header), not dropped as too big."""
    elements = [*VALID[:5], [0.0] * 32, b"x" * 64, b"x" * 64, b"x" * 64, b"x" * 3, b"x" * 3,
                b"x" * 3]
    data = msgpack.packb(elements)
    assert len(data) == MAX_REQUEST_BYTES
    err = _error(data)
    assert (err.code, err.header) == (MALFORMED, HEADER)


@pytest.mark.parametrize("data", [
    b"", b"\xc1", b"\x9d", b"\x92\x01", b"\xcb\x00", b"\xd9\x05ab", msgpack.packb(VALID)[:-1],
    msgpack.packb(VALID)[:20]], ids=repr)
def test_not_msgpack(data):
    err = _error(data)
    assert (err.code, err.header) == (MALFORMED, None)


@pytest.mark.parametrize("extra", [b"\x00", b"\xc0", msgpack.packb(VALID)])
def test_trailing_bytes(extra):
    err = _error(msgpack.packb(VALID) + extra)
    assert (err.code, err.header) == (MALFORMED, None)


@pytest.mark.parametrize("obj", [None, True, 1, 1.5, "pose", b"pose", {"version": 1},
                                 msgpack.ExtType(1, b"")], ids=repr)
def test_not_an_array(obj):
    err = _error(msgpack.packb(obj))
    assert (err.code, err.header) == (MALFORMED, None)


@pytest.mark.parametrize("n", range(5))
def test_short_arrays(n):
    err = _error(msgpack.packb(VALID[:n]))
    assert (err.code, err.header) == (MALFORMED, None)


@pytest.mark.parametrize("version", [0, 1, 3, 255, 70000, -1])
def test_wrong_version(version):
    err = _error(msgpack.packb(_with(0, version)))
    assert (err.code, err.header) == (BAD_VERSION, HEADER)


def test_wrong_version_is_reported_whatever_follows_the_header():
    """Elements 0–4 mean the same in every version: a later version's shape gets BAD_VERSION."""
    for elements in ([3, 1, *HEADER], [3, 1, *HEADER, "future", [1, 2], {"k": 1}],
                     [1, 1, *HEADER, *VALID[5:11], None]):
        err = _error(msgpack.packb(elements))
        assert (err.code, err.header) == (BAD_VERSION, HEADER)


@pytest.mark.parametrize("kind", [0, REPLY, NOTICE, 4, 200, -3])
def test_wrong_type(kind):
    err = _error(msgpack.packb(_with(1, kind)))
    assert (err.code, err.header) == (BAD_TYPE, HEADER)


def test_server_message_types_sent_to_the_server_are_bad_type():
    reply = Reply(*HEADER, 1, 2, 0, 0, *([(0.0, 0.0, 0.0)] * 3), 0.0, 0.0, 0.0,
                  *([(0.0, 0.0, 0.0)] * 3), 0.0, 0.0, 0.0, 1, (0.0, 0.0, 0.0))
    for data in (encode_reply(reply), encode_notice(Notice(*HEADER, 5), Tagger(KEY))):
        err = _error(data)
        assert (err.code, err.header) == (BAD_TYPE, HEADER)


@pytest.mark.parametrize("elements", [VALID[:5], VALID[:11], VALID[:12], [*VALID, None],
                                      [*VALID, 0, 0]],
                         ids=lambda e: f"{len(e)} elements")
def test_wrong_element_count(elements):
    err = _error(msgpack.packb(elements))
    assert (err.code, err.header) == (MALFORMED, HEADER)


@pytest.mark.parametrize(("index", "value"), [
    (0, "1"), (0, 1.0), (0, True), (0, None), (0, [1]),
    (1, "1"), (1, 1.0), (1, True), (1, None),
    (2, -1), (2, U32), (2, "7"), (2, 7.0), (2, True), (2, None), (2, b"\x07"), (2, {"a": 1}),
    (3, -1), (3, U32), (3, 1 << 40), (3, "3"), (3, 3.0), (3, False), (3, None),
    (4, -1), (4, MAX_TIMESTAMP_US + 1), (4, (1 << 64) - 1), (4, 1.0), (4, True), (4, "1000"),
    (4, [1000]),
], ids=repr)
def test_malformed_header_has_no_header(index, value):
    err = _error(msgpack.packb(_with(index, value)))
    assert (err.code, err.header) == (MALFORMED, None)


EMPTY_EXT = msgpack.ExtType(5, b"")
BAD_FIELDS = {
    5: ["x", [[1.0], [2.0], [3.0]], [1.0, 2.0], [1.0, 2.0, 3.0, 4.0], [True, 0.0, 0.0],
        [1.0, "2", 3.0], [1.0, None, 3.0], {"x": 1.0}, None, 1.0, b"abc", EMPTY_EXT,
        [1.0, 2.0, EMPTY_EXT]],
    6: ["q", [[0.0], [0.0], [0.0], [1.0]], [0.0, 0.0, 1.0], [0.0] * 5, [0.0, 0.0, 0.0, True],
        [0.0, 0.0, 0.0, None], {"w": 1.0}, None, 1.0, EMPTY_EXT],
    7: ["fast", [60000.0], True, False, None, {"rpm": 1.0}, b"\x01", EMPTY_EXT],
    8: [1, 0, 1.0, "yes", None, [True], {"on": True}, EMPTY_EXT],
    9: [[1.0, 2.0], [1.0, 2.0, 3.0, 4.0], "v", [True, 0.0, 0.0], [[1.0], 2.0, 3.0], {"v": 0},
        0, 0.0, False, EMPTY_EXT],
    10: [-1, U32, 1 << 63, 1.0, True, None, "0", [0], {"f": 0}, EMPTY_EXT],
    11: [-1, U32, 1 << 63, 1.0, True, None, "0", [0], {"s": 0}, EMPTY_EXT],
    12: [bytes(15), bytes(17), b"", bytes(64), "x" * 16, 16, True, [0] * 16, {"tag": 0},
         EMPTY_EXT],
}
FIELD_NAMES = {5: "position", 6: "orientation", 7: "rpm", 8: "spindle_on", 9: "velocity",
               10: "flags", 11: "stream", 12: "tag"}


@pytest.mark.parametrize(("index", "value"),
                         [(i, v) for i, values in BAD_FIELDS.items() for v in values],
                         ids=lambda x: FIELD_NAMES[x] if isinstance(x, int) and x in
                         FIELD_NAMES else repr(x)[:30])
def test_field_of_wrong_type_is_malformed_with_header(index, value):
    err = _error(msgpack.packb(_with(index, value)))
    assert (err.code, err.header) == (MALFORMED, HEADER)
    assert err.detail


@pytest.mark.parametrize("index", [5, 7, 9, 11, 12])
def test_ext_type_with_data_is_rejected(index):
    err = _error(msgpack.packb(_with(index, msgpack.ExtType(1, b"\x00" * 8))))
    assert (err.code, err.header) == (MALFORMED, None)


def test_timestamp_ext_is_rejected():
    err = _error(msgpack.packb(_with(4, msgpack.Timestamp(1, 0))))
    assert (err.code, err.header) == (MALFORMED, None)


def _splice(index: int, raw: bytes) -> bytes:
    """VALID packed with element ``index`` replaced by the raw msgpack ``raw``."""
    parts = [msgpack.packb(x) for x in VALID]
    parts[index] = raw
    return b"\x9d" + b"".join(parts)


@pytest.mark.parametrize("data", [
    b"\x91" * 511 + b"\xc0",
    b"\x91" * 512,
    b"\x81\xa1a" * 170 + b"\xc0",
    b"\xdc\x00\x01" * 170 + b"\xc0",
    b"\x95" + b"\x91" * 500 + b"\xc0",
    _splice(5, b"\x91" * 400 + b"\xc0"),
    _splice(9, b"\x93" + b"\x91" * 300 + b"\xc0\xc0\xc0"),
    _splice(12, b"\x81\xa1t" * 100 + b"\xc0"),
], ids=lambda d: f"{d[:6].hex()}…({len(d)} bytes)")
def test_nesting_bombs(data):
    assert len(data) <= MAX_REQUEST_BYTES
    err = _error(data)
    assert err.code == MALFORMED


@pytest.mark.parametrize("data", [
    msgpack.packb({str(i): i for i in range(17)}),
    msgpack.packb("x" * 65),
    msgpack.packb(b"x" * 65),
    msgpack.packb(list(range(33))),
    _splice(5, msgpack.packb({f"k{i}": 0 for i in range(17)})),
    _splice(7, msgpack.packb("r" * 100)),
    _splice(12, msgpack.packb(b"t" * 65)),
    _splice(6, msgpack.packb([0.0] * 33)),
    b"\xdc\xff\xff", b"\xdd\xff\xff\xff\xff", b"\xde\xff\xff", b"\xdf\xff\xff\xff\xff",
    b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xc9\xff\xff\xff\xff\x01",
    b"\x9d" + b"\xdd\xff\xff\xff\xff" * 13,
], ids=lambda d: f"{d[:6].hex()}…({len(d)} bytes)")
def test_objects_beyond_the_limits(data):
    err = _error(data)
    assert (err.code, err.header) == (MALFORMED, None)


def test_values_are_not_checked_by_decoding():
    nan = float("nan")
    pose = decode_pose(msgpack.packb(_with(5, [nan, math.inf, -math.inf])))
    assert math.isnan(pose.position[0]) and pose.position[1:] == (math.inf, -math.inf)
    assert check_pose_values(pose) is not None


# -- decode_server_message errors ---------------------------------------------------------------
REPLY_VALID = [2, 2, *HEADER, 11, 12, 0, 3, [1.0, 2.0, 3.0], [0.5, 0.25, 0.0], [0.0, 0.0, 1.0],
               4.0, 0.5, 1000.0, [0.0, 0.0, 1.0], [1.0, 2.0, 3.0], [0.0, 0.0, 0.0], 1.5, 0.01,
               0.002, 9, [0.0, 0.0, -1.0], None]
NOTICE_VALID = [2, 3, *HEADER, 6, 0, None]


def _reply_with(index: int, value: object) -> bytes:
    out = list(REPLY_VALID)
    out[index] = value
    return msgpack.packb(out)


def test_valid_server_messages_decode():
    reply = decode_server_message(msgpack.packb(REPLY_VALID))
    assert type(reply) is Reply and reply.force == (1.0, 2.0, 3.0) and reply.bone_version == 9
    assert reply.status_names() == ["cutting", "contact"]
    notice = decode_server_message(msgpack.packb(NOTICE_VALID))
    assert notice == Notice(*HEADER, 6) and notice.error_name == "bad_tag"
    notice = decode_server_message(msgpack.packb([*NOTICE_VALID[:5], NEW_STREAM, U32 - 1, None]))
    assert notice == Notice(*HEADER, NEW_STREAM, U32 - 1) and notice.error_name == "new_stream"


def test_server_message_too_big():
    err = _error(bytes(MAX_REPLY_BYTES + 1), decode_server_message)
    assert (err.code, err.header) == (TOO_BIG, None)


def test_server_message_version_and_type():
    for version in (1, 3):
        err = _error(msgpack.packb([version, *REPLY_VALID[1:]]), decode_server_message)
        assert (err.code, err.header) == (BAD_VERSION, HEADER)
    for kind in (POSE, 0, 4):
        err = _error(msgpack.packb([2, kind, *REPLY_VALID[2:]]), decode_server_message)
        assert (err.code, err.header) == (BAD_TYPE, HEADER)
    err = _error(msgpack.packb(VALID), decode_server_message)
    assert (err.code, err.header) == (BAD_TYPE, HEADER)


@pytest.mark.parametrize("elements", [
    NOTICE_VALID[:7], [*NOTICE_VALID, None], [*NOTICE_VALID[:5], -1, 0, None],
    [*NOTICE_VALID[:5], 1 << 16, 0, None], [*NOTICE_VALID[:5], "bad_tag", 0, None],
    [*NOTICE_VALID[:5], True, 0, None], [*NOTICE_VALID[:5], 6.0, 0, None],
    [*NOTICE_VALID[:6], -1, None], [*NOTICE_VALID[:6], U32, None],
    [*NOTICE_VALID[:6], None, None], [*NOTICE_VALID[:6], 1.0, None],
    [*NOTICE_VALID[:7], bytes(15)], [*NOTICE_VALID[:7], "t" * 16],
    REPLY_VALID[:23], [*REPLY_VALID, None], REPLY_VALID[:5],
], ids=lambda e: f"{len(e)} elements")
def test_malformed_notice_or_reply_shape(elements):
    err = _error(msgpack.packb(elements), decode_server_message)
    assert (err.code, err.header) == (MALFORMED, HEADER)


# -1 is a valid float: only the integer elements must refuse it.
WRONG_REPLY_ELEMENTS = [
    (i, v) for i in range(5, 24) for v in ("x", True, [1.0, 2.0], -1, {"a": 1}, EMPTY_EXT)
    if not (type(REPLY_VALID[i]) is float and v == -1)]


@pytest.mark.parametrize(("index", "value"), WRONG_REPLY_ELEMENTS, ids=repr)
def test_reply_element_of_wrong_type(index, value):
    err = _error(_reply_with(index, value), decode_server_message)
    assert (err.code, err.header) == (MALFORMED, HEADER)


def test_reply_integer_limits():
    reply = decode_server_message(_reply_with(5, (1 << 64) - 1))
    assert reply.t_recv_us == (1 << 64) - 1
    for index, value in ((8, 1 << 32), (7, 1 << 16)):
        err = _error(_reply_with(index, value), decode_server_message)
        assert (err.code, err.header) == (MALFORMED, HEADER)


def test_read_header():
    assert read_header(msgpack.packb(VALID)) == (2, 1, *HEADER)
    assert read_header(msgpack.packb([9, 2, *HEADER, "anything"])) == (9, 2, *HEADER)
    for data in (b"", b"\xc1", msgpack.packb(VALID[:4]), msgpack.packb(_with(2, -1)),
                 bytes(2000)):
        assert read_header(data) is None


# -- check_pose_values --------------------------------------------------------------------------
GOOD = Pose(1, 1, 1, (10.0, -20.0, 30.0), (0.0, 0.0, 0.6, 0.8), 60000.0, True, (1.0, 2.0, 3.0))


def test_normal_poses_have_usable_values():
    assert check_pose_values(GOOD) is None
    assert check_pose_values(GOOD._replace(velocity=None)) is None
    assert check_pose_values(GOOD._replace(rpm=-1e7, position=(1e9, -1e9, 0.0))) is None
    assert check_pose_values(GOOD._replace(orientation=(0.0, 0.0, 0.0, 0.5))) is None
    assert check_pose_values(GOOD._replace(orientation=(0.0, 0.0, 0.0, 1.5))) is None
    assert check_pose_values(GOOD._replace(orientation=(0.0, 0.0, 0.9, 0.9))) is None


@pytest.mark.parametrize("field", ["position", "orientation", "velocity"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 2e9, -1e300])
def test_non_finite_vector_components(field, bad):
    for i in range(len(getattr(GOOD, field))):
        values = list(getattr(GOOD, field))
        values[i] = bad
        message = check_pose_values(GOOD._replace(**{field: tuple(values)}))
        assert message is not None and field in message, (i, message)


@pytest.mark.parametrize("rpm", [math.nan, math.inf, -math.inf, 1e7 + 1, -1.0000001e7, 1e300])
def test_rpm_out_of_range(rpm):
    message = check_pose_values(GOOD._replace(rpm=rpm))
    assert message is not None and "rpm" in message


@pytest.mark.parametrize("q", [(0.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.4), (0.0, 0.0, 0.0, 1.6),
                               (1.0, 1.0, 1.0, 1.0), (1e-300, 0.0, 0.0, 0.0), (0.3, 0.1, 0.1, 0.1)])
def test_quaternion_of_bad_norm(q):
    message = check_pose_values(GOOD._replace(orientation=q))
    assert message is not None and "orientation" in message and "norm" in message


# -- fuzz ---------------------------------------------------------------------------------------
msgpack_objects = st.recursive(
    st.none() | st.booleans() | st.integers(-(1 << 63), (1 << 64) - 1) | st.floats()
    | st.text(max_size=70) | st.binary(max_size=70),
    lambda children: st.lists(children, max_size=35)
    | st.dictionaries(st.text(max_size=6), children, max_size=18),
    max_leaves=30)


def _assert_well_typed(m):
    assert type(m) in (Pose, Reply, Notice)
    for name, value in m._asdict().items():
        if name == "tag":
            assert value is None or (type(value) is bytes and len(value) == TAG_BYTES)
        elif name == "velocity" and value is None:
            pass
        elif name == "spindle_on":
            assert type(value) is bool
        elif isinstance(value, tuple):
            assert len(value) in (3, 4) and all(type(x) is float for x in value), name
        else:
            assert type(value) in (int, float), name
            if type(value) is int:
                assert value >= 0, name


def _decodes_or_protocol_error(data: bytes) -> None:
    for decode in (decode_pose, decode_server_message):
        try:
            result = decode(data)
        except ProtocolError as exc:
            assert exc.code in (TOO_BIG, MALFORMED, BAD_VERSION, BAD_TYPE)
            assert exc.header is None or len(exc.header) == 3
        else:
            _assert_well_typed(result)
            if decode is decode_pose:
                assert type(result) is Pose
            else:
                assert type(result) in (Reply, Notice)
        header = read_header(data)
        assert header is None or len(header) == 5


@given(st.binary(max_size=600))
def test_fuzz_arbitrary_bytes(data):
    _decodes_or_protocol_error(data)


@given(msgpack_objects)
def test_fuzz_arbitrary_msgpack_objects(obj):
    _decodes_or_protocol_error(msgpack.packb(obj))


@given(index=st.integers(0, 12), obj=msgpack_objects)
def test_fuzz_one_pose_element_replaced(index, obj):
    _decodes_or_protocol_error(msgpack.packb(_with(index, obj)))


@given(index=st.integers(0, 23), obj=msgpack_objects)
def test_fuzz_one_reply_element_replaced(index, obj):
    elements = list(REPLY_VALID)
    elements[index] = obj
    _decodes_or_protocol_error(msgpack.packb(elements))


@given(data=st.binary(min_size=1, max_size=300), position=st.integers(0, 10_000),
       junk=st.binary(max_size=20))
def test_fuzz_mutated_vectors(data, position, junk):
    for vec in VECTORS:
        raw = bytearray.fromhex(vec["hex"])
        i = position % len(raw)
        raw[i:i + len(junk)] = junk
        _decodes_or_protocol_error(bytes(raw))
    _decodes_or_protocol_error(data)


# -- sequence numbers ---------------------------------------------------------------------------
HALF = 1 << 31


@given(a=uint32, d=st.integers(1, HALF - 1))
def test_seq_after_within_half_the_circle(a, d):
    b = (a + d) % U32
    assert seq_after(b, a)
    assert not seq_after(a, b)


@given(a=uint32)
def test_seq_after_equal_and_opposite(a):
    assert not seq_after(a, a)
    opposite = (a + HALF) % U32
    assert not seq_after(opposite, a)
    assert not seq_after(a, opposite)


@given(a=uint32, b=uint32)
def test_seq_after_is_antisymmetric(a, b):
    assert not (seq_after(a, b) and seq_after(b, a))
    if a != b and (a - b) % U32 != HALF:
        assert seq_after(a, b) != seq_after(b, a)


def test_seq_after_across_the_wrap():
    assert seq_after(0, U32 - 1)
    assert seq_after(5, U32 - 5)
    assert not seq_after(U32 - 1, 0)
    assert seq_after(HALF - 1, 0) and not seq_after(HALF, 0)


@given(a=uint32, step=st.integers(0, 3 * U32))
def test_seq_next(a, step):
    n = seq_next(a, step)
    assert 0 <= n < U32 and n == (a + step) % U32


def test_seq_next_wraps():
    assert seq_next(U32 - 1) == 0
    assert seq_next(0) == 1
    assert seq_next(U32 - 2, 3) == 1


# -- the hot loop's compiled packet path (server/hotloop/wire.py) --------------------------------
def _compiled_decode(datagram: bytes):
    """(decoded?, pose ints, pose float bits) from wire.decode_pose_into."""
    from burrforce.server.hotloop import wire

    rx, pose_i, pose_f, _, _ = wire.new_buffers()
    n = min(len(datagram), len(rx))
    rx[:n] = list(datagram[:n])
    ok = wire.decode_pose_into(rx, len(datagram), pose_i, pose_f)
    return ok, pose_i.tolist(), pose_f.view("u8").tolist()


def _reference_arrays(pose: Pose):
    """What the compiled decoder must produce for ``pose`` (wire.pose_arrays)."""
    import numpy as np

    from burrforce.server.hotloop import wire

    pose_i = np.zeros(wire.POSE_INTS, np.int64)
    pose_f = np.zeros(wire.POSE_FLOATS)
    wire.pose_arrays(pose, pose_i, pose_f)
    return pose_i.tolist(), pose_f.view("u8").tolist()


@given(pose=poses(any_float), key=keys_or_none)
def test_compiled_decoder_agrees_on_every_canonical_pose(pose, key):
    """Every POSE the reference encoder writes is the compiled decoder's, bit for bit
    (NaN, ±inf and -0.0 included), and means what the general decoder says it means."""
    data = encode_pose(pose, Tagger(key) if key is not None else None)
    ok, ints, bits = _compiled_decode(data)
    assert ok
    assert (ints, bits) == _reference_arrays(decode_pose(data))


def _mutated_pose_datagrams():
    base = encode_pose(Pose(7, 9, 1 << 40, (1.0, -2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 6e4, True,
                            (0.5, 0.0, -0.5), 1, 0xC0FFEE), Tagger(KEY))
    plain = encode_pose(Pose(7, 9, 11, (1.0, -2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 6e4, False))
    return st.sampled_from([base, plain]).flatmap(lambda data: st.one_of(
        st.binary(max_size=600),
        st.tuples(st.integers(0, len(data) - 1), st.integers(0, 255)).map(
            lambda iv: data[:iv[0]] + bytes([iv[1]]) + data[iv[0] + 1:]),
        st.tuples(st.integers(0, len(data) - 1), st.integers(0, 7)).map(
            lambda ib: data[:ib[0]] + bytes([data[ib[0]] ^ (1 << ib[1])]) + data[ib[0] + 1:]),
        st.integers(0, len(data)).map(lambda n: data[:n]),
        st.binary(min_size=1, max_size=40).map(lambda extra: data + extra),
        st.tuples(st.integers(0, len(data)), st.binary(min_size=1, max_size=9)).map(
            lambda ix: data[:ix[0]] + ix[1] + data[ix[0]:]),
    ))


@given(_mutated_pose_datagrams())
def test_compiled_decoder_takes_only_what_the_general_decoder_takes(data):
    """On any bytes, the compiled decoder either declines (the dispatcher then asks the
    general decoder, so every error code and counter is its) or decodes exactly what the
    general decoder decodes."""
    ok, ints, bits = _compiled_decode(data)
    if ok:
        assert (ints, bits) == _reference_arrays(decode_pose(data))


@given(pose=poses(friendly), tag=tags, data=st.data())
def test_compiled_decoder_declines_or_agrees_on_non_canonical_forms(pose, tag, data):
    parts = [*_draw_header(data, POSE, pose), _draw_vec(data, pose.position),
             _draw_vec(data, pose.orientation), _draw_float(data, pose.rpm),
             b"\xc3" if pose.spindle_on else b"\xc2",
             b"\xc0" if pose.velocity is None else _draw_vec(data, pose.velocity),
             _draw_int(data, pose.flags), _draw_int(data, pose.stream), _draw_tag(data, tag)]
    datagram = _draw_array(data, parts)
    assume(len(datagram) <= MAX_REQUEST_BYTES)
    ok, ints, bits = _compiled_decode(datagram)
    if ok:
        assert (ints, bits) == _reference_arrays(decode_pose(datagram))


int63 = st.integers(0, (1 << 63) - 1)


@given(reply=replies(any_float).flatmap(lambda r: st.builds(
           r._replace, t_recv_us=int63, t_send_us=int63, bone_version=int63)),
       key=keys_or_none)
def test_compiled_encoder_is_byte_identical_to_the_reference(reply, key):
    """wire.encode_reply_into + the MAC writes exactly encode_reply's bytes (any float64,
    every integer width the server's fields take)."""
    import numpy as np

    from burrforce.server.hotloop import wire

    tagger = Tagger(key) if key is not None else None
    _, _, _, tx, reply_i = wire.new_buffers()
    reply_f = np.zeros(wire.REPLY_FLOATS)
    reply_i[:] = (*reply[:7], reply.bone_version)
    reply_f[:] = [x for name in Reply._fields[7:-1] if name != "bone_version"
                  for x in (getattr(reply, name) if isinstance(getattr(reply, name), tuple)
                            else (getattr(reply, name),))]
    n = wire.encode_reply_into(tx, reply_i, reply_f, tagger is not None)
    out = memoryview(tx)[:n]
    if tagger is not None:
        tagger.sign(out)
    assert bytes(out) == encode_reply(reply, tagger)
