"""Write the wire protocol's golden vectors (vectors.json) with burrforce.proto's encoders.

Run from anywhere with burrforce installed::

    python proto/vectors/make_vectors.py            # write vectors.json
    python proto/vectors/make_vectors.py --check    # compare only; exit 1 on a difference

The vectors are a contract with every other implementation of the protocol: once published,
a case's bytes never change within a protocol version. This script therefore refuses to
change the bytes of a case already in vectors.json unless given ``--force`` (a deliberate act,
for a new protocol version); adding cases and rewording descriptions need no flag.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, NamedTuple

from burrforce.proto.codec import (
    encode_bad_version_v1,
    encode_notice,
    encode_pose,
    encode_reply,
)
from burrforce.proto.messages import (
    BAD_TAG,
    BAD_VALUE,
    BAD_VERSION,
    FLAG_NO_CARVE,
    NEW_STREAM,
    OK,
    STATUS_CLAMPED,
    STATUS_CONTACT,
    STATUS_CUTTING,
    STATUS_SHAFT_CONTACT,
    UNKNOWN_SESSION,
    VERSION,
    VERSION_1,
    WRONG_STREAM,
    Notice,
    Pose,
    Reply,
)
from burrforce.proto.tag import Tagger

#: The fixed key of every tagged vector (never use it for a real session).
KEY_HEX = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff"
PATH = Path(__file__).with_name("vectors.json")
#: cos 45° = sin 45°: a 90° turn about one axis (its float64 repr round-trips through JSON).
H = 0.7071067811865476


class Case(NamedTuple):
    name: str
    description: str
    message: Pose | Reply | Notice
    tagged: bool
    #: the protocol version on the wire: VERSION_1 only for the v1-shaped BAD_VERSION notice
    #: a v2 server answers a v1 datagram with (its fields have no ``stream``).
    version: int = VERSION


CASES: tuple[Case, ...] = (
    Case("pose_tagged",
         "POSE, tagged: typical values, spindle on at 60000 rpm, no velocity (the server "
         "estimates it), flags 0, stream 305419896 (uint32 form); orientation a 90 degree "
         "turn about z.",
         Pose(session=7, seq=1, t_client_us=1_000_000, position=(12.5, -0.25, 30.0),
              orientation=(0.0, 0.0, H, H), rpm=60000.0, spindle_on=True,
              stream=0x12345678), True),
    Case("pose_untagged_velocity_flags",
         "POSE, untagged: a velocity, flags NO_CARVE|4 (6: bit 2 is reserved, receivers ignore "
         "it), spindle off, session, seq and stream in msgpack uint16, uint8 and positive "
         "fixint form (stream 5).",
         Pose(session=300, seq=200, t_client_us=123_456_789, position=(0.125, 0.0625, -2.5),
              orientation=(0.0, 0.0, 0.0, 1.0), rpm=0.0, spindle_on=False,
              velocity=(1.5, -0.75, 0.0), flags=4 | FLAG_NO_CARVE, stream=5), False),
    Case("pose_extremes",
         "POSE, tagged: session and seq 4294967295 (uint32 form: the seq about to wrap), "
         "t_client_us above 2^32 (uint64 form), negative coordinates, reverse spin "
         "(negative rpm), a velocity, flags RESET_VELOCITY (1), stream 65536 (uint32 form).",
         Pose(session=4_294_967_295, seq=4_294_967_295, t_client_us=5_000_000_000_123,
              position=(-1000.5, -0.125, -250.0), orientation=(-H, 0.0, 0.0, H),
              rpm=-12345.5, spindle_on=True, velocity=(-3.25, 8.0, -0.5), flags=1,
              stream=65536), True),
    Case("pose_largest",
         "POSE, tagged, as long as a POSE gets (153 bytes): session, seq, flags and stream "
         "4294967295 (uint32 forms; receivers ignore the reserved flag bits), t_client_us "
         "2^63 - 1 (uint64 form), a velocity.",
         Pose(session=4_294_967_295, seq=4_294_967_295, t_client_us=(1 << 63) - 1,
              position=(-0.5, 1e9, 3.0e-5), orientation=(0.5, -0.5, 0.5, -0.5),
              rpm=1e7, spindle_on=True, velocity=(-1e9, 0.1, 2.0), flags=4_294_967_295,
              stream=4_294_967_295), True),
    Case("pose_hello",
         "POSE, tagged: a hello (stream 0): asks the server for a stream; the server answers "
         "NOTICE NEW_STREAM and does not tick it. Spindle on at 60000 rpm, no velocity.",
         Pose(session=7, seq=1, t_client_us=999_000, position=(12.5, -0.25, 30.0),
              orientation=(0.0, 0.0, 0.0, 1.0), rpm=60000.0, spindle_on=True, stream=0), True),
    Case("reply_tagged",
         "REPLY, tagged: error OK and a nonzero value in every other field; status "
         "CUTTING|CONTACT|CLAMPED|SHAFT_CONTACT (43); timestamps above 2^32.",
         Reply(session=7, seq=1, t_client_us=1_000_000, t_recv_us=5_000_000_017,
               t_send_us=5_000_000_042, error=OK,
               status=STATUS_CUTTING | STATUS_CONTACT | STATUS_CLAMPED | STATUS_SHAFT_CONTACT,
               force=(1.25, -0.5, 2.75), resistive=(0.75, -0.125, 1.5),
               torque=(-0.0625, 0.03125, 0.25), power_w=12.5, vibration_amplitude=0.375,
               vibration_frequency_hz=1000.0, vibration_axis=(0.0, H, H),
               proxy_position=(12.25, -0.375, 29.5), proxy_velocity=(-1.5, 2.0, 0.5),
               coupling_stiffness=2.5, coupling_damping=0.0078125, removed_mm3=0.046875,
               bone_version=123_456, feed_velocity=(4.0, -2.5, -1.0)), True),
    Case("reply_largest",
         "REPLY, tagged, as long as a v2 server's REPLY gets (321 bytes): session and seq "
         "4294967295, every timestamp and bone_version above 2^32 (uint64 forms), every status "
         "bit v2 defines (127). The field kinds allow 6 bytes more (a uint16 error, a uint32 "
         "status): 327.",
         Reply(session=4_294_967_295, seq=4_294_967_295, t_client_us=(1 << 63) - 1,
               t_recv_us=(1 << 63) - 2, t_send_us=(1 << 63) - 1, error=OK, status=127,
               force=(-1.25, 0.5, -2.75), resistive=(-0.75, 0.125, 1.5),
               torque=(0.0625, -0.03125, -0.25), power_w=1e-3, vibration_amplitude=2.5,
               vibration_frequency_hz=3000.0, vibration_axis=(-H, 0.0, -H),
               proxy_position=(-1e6, 2e-6, 0.5), proxy_velocity=(1.5, -2.0, -0.5),
               coupling_stiffness=1e3, coupling_damping=-0.0, removed_mm3=1e-9,
               bone_version=(1 << 40) + 1, feed_velocity=(-4.0, 2.5, 1.0)), True),
    Case("reply_bad_value",
         "REPLY, untagged: error BAD_VALUE (7) as SPEC.md 3.2 defines an error reply: status 0, "
         "every vector and float field zero (0.0); timestamps and bone_version as usual.",
         Reply(session=9, seq=77, t_client_us=2_000_000, t_recv_us=3_000_000,
               t_send_us=3_000_010, error=BAD_VALUE, status=0,
               force=(0.0, 0.0, 0.0), resistive=(0.0, 0.0, 0.0), torque=(0.0, 0.0, 0.0),
               power_w=0.0, vibration_amplitude=0.0, vibration_frequency_hz=0.0,
               vibration_axis=(0.0, 0.0, 0.0), proxy_position=(0.0, 0.0, 0.0),
               proxy_velocity=(0.0, 0.0, 0.0), coupling_stiffness=0.0, coupling_damping=0.0,
               removed_mm3=0.0, bone_version=5, feed_velocity=(0.0, 0.0, 0.0)), False),
    Case("notice_bad_tag",
         "NOTICE, tagged (the session is known): error BAD_TAG (6), stream 0.",
         Notice(session=7, seq=2, t_client_us=1_001_000, error=BAD_TAG), True),
    Case("notice_unknown_session",
         "NOTICE, untagged (no such session, so no key): error UNKNOWN_SESSION (5), stream 0.",
         Notice(session=12345, seq=0, t_client_us=0, error=UNKNOWN_SESSION), False),
    Case("notice_new_stream",
         "NOTICE, tagged: error NEW_STREAM (11), the answer to pose_hello (its seq and "
         "t_client_us echoed): stream 305419896 is open, the client puts it in element 11 of "
         "its next POSEs.",
         Notice(session=7, seq=1, t_client_us=999_000, error=NEW_STREAM, stream=0x12345678),
         True),
    Case("notice_new_stream_replayed",
         "NOTICE, tagged: a NEW_STREAM (11) echoing pose_hello's seq (1) but not its "
         "t_client_us: an old answer replayed to a client that started its seqs again at 1. "
         "Authentic, about the right session, yet a client that sent pose_hello MUST ignore "
         "it: it takes a NEW_STREAM only if both seq and t_client_us echo a hello it sent "
         "since it lost its stream (SPEC.md 5.2), and notice_new_stream does.",
         Notice(session=7, seq=1, t_client_us=500_000, error=NEW_STREAM, stream=0x11223344),
         True),
    Case("notice_wrong_stream",
         "NOTICE, tagged: error WRONG_STREAM (12): the POSE's stream 305419896 is not (or no "
         "longer) open; the client sends a hello.",
         Notice(session=7, seq=3, t_client_us=1_002_000, error=WRONG_STREAM,
                stream=0x12345678), True),
    Case("notice_bad_version_v1",
         "NOTICE in the version-1 shape [1, 3, session, seq, t_client_us, 3, nil], untagged: "
         "what a v2 server answers a v1 datagram with (error BAD_VERSION), so a v1 client can "
         "say \"update me\". A v2 decoder rejects it with BAD_VERSION; its fields have no "
         "stream (top-level \"version\": 1).",
         Notice(session=7, seq=1, t_client_us=1_000_000, error=BAD_VERSION), False,
         VERSION_1),
)


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    return value


def _type(message: Pose | Reply | Notice) -> str:
    return {Pose: "pose", Reply: "reply", Notice: "notice"}[type(message)]


def encode(message: Pose | Reply | Notice, tagger: Tagger | None,
           version: int = VERSION) -> bytes:
    if version == VERSION_1:
        assert isinstance(message, Notice) and message.error == BAD_VERSION and tagger is None
        return encode_bad_version_v1(message.session, message.seq, message.t_client_us)
    if isinstance(message, Pose):
        return encode_pose(message, tagger)
    if isinstance(message, Reply):
        return encode_reply(message, tagger)
    return encode_notice(message, tagger)


def build() -> list[dict[str, Any]]:
    """The vectors, as written to vectors.json."""
    tagger = Tagger(bytes.fromhex(KEY_HEX))
    out = []
    for case in CASES:
        fields = {k: _jsonable(v) for k, v in case.message._asdict().items()
                  if k != "tag" and not (k == "stream" and case.version == VERSION_1)}
        datagram = encode(case.message, tagger if case.tagged else None, case.version)
        out.append({"name": case.name, "description": case.description,
                    "version": case.version, "type": _type(case.message),
                    "key_hex": KEY_HEX if case.tagged else None,
                    "fields": fields, "hex": datagram.hex()})
    return out


def dumps(vectors: list[dict[str, Any]]) -> str:
    return json.dumps(vectors, indent=2, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="compare with vectors.json, write nothing; exit 1 if they differ")
    parser.add_argument("--force", action="store_true",
                        help="allow changing the bytes of existing cases (a new protocol "
                             "version only)")
    args = parser.parse_args(argv)
    text = dumps(build())
    old = PATH.read_text(encoding="utf-8") if PATH.exists() else None
    if args.check:
        if old == text:
            print(f"{PATH.name}: up to date")
            return 0
        print(f"{PATH.name}: differs from what the encoders produce", file=sys.stderr)
        return 1
    if old is not None:
        old_hex = {v["name"]: v["hex"] for v in json.loads(old)}
        changed = [v["name"] for v in build() if old_hex.get(v["name"], v["hex"]) != v["hex"]]
        if changed and not args.force:
            print(f"refusing to change the bytes of {', '.join(changed)}: the vectors are a "
                  "contract. If the protocol version changed, rerun with --force.",
                  file=sys.stderr)
            return 1
    PATH.write_text(text, encoding="utf-8")
    print(f"wrote {len(CASES)} vectors to {PATH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
