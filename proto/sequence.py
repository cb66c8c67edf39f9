"""Sequence numbers: unsigned 32-bit, compared with wrap-around (RFC 1982 serial numbers)."""

from __future__ import annotations

from .messages import SEQ_MODULUS

_HALF = SEQ_MODULUS >> 1


def seq_after(a: int, b: int) -> bool:
    """True if sequence number ``a`` is newer than ``b``: 0 < (a − b) mod 2³² < 2³¹.

    Numbers exactly 2³¹ apart are incomparable; they count as not newer (stale).
    """
    return 0 < (a - b) % SEQ_MODULUS < _HALF


def seq_next(a: int, step: int = 1) -> int:
    """The sequence number ``step`` after ``a``."""
    return (a + step) % SEQ_MODULUS
