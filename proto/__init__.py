"""burrforce wire protocol: the language-neutral spec (SPEC.md), codec, frames, golden vectors."""

from .codec import (
    ProtocolError,
    check_pose_values,
    decode_pose,
    decode_server_message,
    encode_notice,
    encode_pose,
    encode_reply,
)
from .frames import FRAMES, Frame, Transform, frame
from .messages import VERSION, Notice, Pose, Reply
from .sequence import seq_after, seq_next
from .tag import Tagger, new_key, parse_key

__all__ = ["FRAMES", "VERSION", "Frame", "Notice", "Pose", "ProtocolError", "Reply", "Tagger",
           "Transform", "check_pose_values", "decode_pose", "decode_server_message",
           "encode_notice", "encode_pose", "encode_reply", "frame", "new_key", "parse_key",
           "seq_after", "seq_next"]
