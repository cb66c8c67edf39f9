"""A token bucket: the rate limits of the hot loop (notices, the main socket's budget)."""

from __future__ import annotations


class TokenBucket:
    """``rate_hz`` tokens a second, at most ``burst`` saved up; starts full. Plain attributes
    and no allocation: it is asked on the datagram path.

    A clock that steps back refills nothing (and takes nothing back)."""

    __slots__ = ("at_ns", "burst", "rate_hz", "tokens")

    def __init__(self, rate_hz: float, burst: float) -> None:
        self.rate_hz = rate_hz
        self.burst = burst
        self.tokens = burst
        self.at_ns = 0

    def refill(self, now_ns: int) -> float:
        """Add what accrued since the last call; returns the tokens now available."""
        if now_ns > self.at_ns:
            self.tokens = min(self.burst,
                              self.tokens + (now_ns - self.at_ns) * 1e-9 * self.rate_hz)
            self.at_ns = now_ns
        return self.tokens

    def take(self, now_ns: int) -> bool:
        """Take a token if one is available."""
        if self.refill(now_ns) < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def due_s(self, now_ns: int) -> float:
        """Seconds until a token is available (≤ 0: one is)."""
        return (1.0 - self.refill(now_ns)) / self.rate_hz

    def reset(self) -> None:
        self.tokens = self.burst
