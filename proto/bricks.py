"""The brick-delta message (``GET /v1/sessions/{id}/deltas``): encoding and decoding.

The bricks of a bone changed since a version, with their remaining density, so an engine can
update its own copy or mesh of the bone. The format (fields, byte layout, order, paging, how
to apply it) is documented in ``burrforce.server.bone.deltas``, which builds the messages;
this module is the part both sides share.

Bone generations: every message carries ``generation``, the number of the bone it is of
(new on each load, reset or restore, since bone versions then restart at 0). A client keeps
(generation, version) and asks with both; when its generation is not the bone's any more
the answer is ``full``: set the whole copy to 0 (reallocated to ``grid_shape``), apply the
bricks, keep the new generation and go on from ``next_since`` as usual.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np

FORMAT = "burrforce-bricks"
FORMAT_VERSION = 1
#: Voxels per brick edge, and per brick.
BRICK = 8
BRICK_VOXELS = BRICK ** 3


def encode_delta(d: dict[str, Any]) -> bytes:
    """``d`` (from :func:`brick_delta`, or decoded) as one msgpack message; ``bricks`` and
    ``remaining`` go as ``bin`` (numpy arrays are converted to the wire's byte layout)."""
    out = dict(d)
    if isinstance(out.get("bricks"), np.ndarray):
        out["bricks"] = np.asarray(out["bricks"]).astype("<i4").tobytes()
    if isinstance(out.get("remaining"), np.ndarray):
        out["remaining"] = np.asarray(out["remaining"]).astype(np.uint8).tobytes()
    return msgpack.packb(out, use_bin_type=True)


def decode_delta(b: bytes) -> dict[str, Any]:
    """A message from :func:`encode_delta` → a dict whose ``bricks`` is int32 (count, 3) and
    ``remaining`` uint8 (count, 8, 8, 8) (writable numpy arrays).

    Raises
    ------
    ValueError
        Not msgpack, not this format or version, or arrays that disagree with ``count``.
    """
    try:
        d = msgpack.unpackb(b, raw=False)
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise ValueError(f"not a msgpack brick delta: {exc}") from None
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ValueError(f"not a {FORMAT} message")
    if d.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{FORMAT} format_version {d.get('format_version')!r} is not "
                         f"supported (this reader knows {FORMAT_VERSION})")
    count = d.get("count")
    bricks, remaining = d.get("bricks"), d.get("remaining")
    if isinstance(count, bool) or not isinstance(count, int) or count < 0 \
            or not isinstance(bricks, bytes) or not isinstance(remaining, bytes) \
            or len(bricks) != 12 * count or len(remaining) != BRICK_VOXELS * count \
            or d.get("brick") != BRICK:
        raise ValueError(f"malformed {FORMAT} message: count, brick, bricks and remaining "
                         "disagree")
    d["bricks"] = np.frombuffer(bricks, dtype="<i4").reshape(count, 3).astype(np.int32)
    d["remaining"] = np.frombuffer(remaining, dtype=np.uint8).reshape(
        count, BRICK, BRICK, BRICK).copy()
    return d
