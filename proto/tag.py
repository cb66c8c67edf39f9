"""Datagram tags: HMAC-SHA256 (RFC 2104) of a datagram's bytes, truncated to 16 bytes.

The tag is the datagram's last element, a msgpack ``bin 8`` of 16 bytes, so its 16 bytes are
the datagram's last 16 bytes; the MAC covers every byte before them (the bin header included).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

from .messages import TAG_BYTES

#: Key length this project generates, bytes (any length is valid HMAC).
KEY_BYTES = 32
#: The two bytes before a 16-byte tag: msgpack bin 8, length 16.
TAG_HEADER = b"\xc4\x10"
_BLOCK = 64  # SHA-256 block size


def new_key() -> bytes:
    """A fresh random session key."""
    return secrets.token_bytes(KEY_BYTES)


def parse_key(text: str) -> bytes:
    """A key from its hex form (as REST and the CLI show it).

    Raises:
        ValueError: not hex, or empty.
    """
    try:
        key = bytes.fromhex(text.strip())
    except ValueError:
        raise ValueError("a session key is hex digits (e.g. 64 of them for 32 bytes)") from None
    if not key:
        raise ValueError("a session key must not be empty")
    return key


class Tagger:
    """Signs and verifies datagrams with one key.

    HMAC is computed from precomputed inner and outer SHA-256 states (RFC 2104's own
    optimization): ~0.8 µs per datagram against ~2.7 µs for ``hmac.digest``.
    """

    __slots__ = ("_inner", "_outer")

    def __init__(self, key: bytes) -> None:
        if not isinstance(key, (bytes, bytearray)) or not key:
            raise ValueError("a session key must be non-empty bytes")
        if len(key) > _BLOCK:
            key = hashlib.sha256(key).digest()
        padded = bytes(key).ljust(_BLOCK, b"\0")
        self._inner = hashlib.sha256(bytes(b ^ 0x36 for b in padded))
        self._outer = hashlib.sha256(bytes(b ^ 0x5C for b in padded))

    def mac(self, data: bytes | bytearray | memoryview) -> bytes:
        """The 16-byte tag of ``data`` (the bytes before the tag)."""
        inner = self._inner.copy()
        inner.update(data)
        outer = self._outer.copy()
        outer.update(inner.digest())
        return outer.digest()[:TAG_BYTES]

    def sign(self, datagram: bytearray) -> None:
        """Fill the last 16 bytes of ``datagram`` (encoded with a placeholder tag) in place."""
        datagram[-TAG_BYTES:] = self.mac(memoryview(datagram)[:-TAG_BYTES])

    def verify(self, datagram: bytes) -> bool:
        """True if ``datagram`` ends with a tag element whose tag is right."""
        if len(datagram) < TAG_BYTES + 2 or \
                datagram[-TAG_BYTES - 2:-TAG_BYTES] != TAG_HEADER:
            return False
        expected = self.mac(memoryview(datagram)[:-TAG_BYTES])
        return hmac.compare_digest(expected, datagram[-TAG_BYTES:])
