"""argparse types shared by the commands and the benchmarks (`cli`, `bench`): numbers in a range,
with messages that say which. Below both, so a benchmark never imports the command line."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T", int, float)


def float_at_least(minimum: float, inclusive: bool) -> Callable[[str], float]:
    """A finite float ≥ minimum (or > minimum)."""
    relation = "≥" if inclusive else ">"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(value) or value < minimum or (value == minimum and not inclusive):
            raise argparse.ArgumentTypeError(
                f"must be a finite number {relation} {minimum:g}, got {text}")
        return value

    return parse


def float_in(low: float, high: float, what: str, unit: str = "") -> Callable[[str], float]:
    """A float in [low, high]; ``what`` and ``unit`` name it in the message."""
    suffix = f" {unit}" if unit else ""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not low <= value <= high:  # also refuses NaN
            raise argparse.ArgumentTypeError(
                f"{what} must be in [{low:g}, {high:g}]{suffix}, got {text}")
        return value

    return parse


def int_in(low: int, high: int, what: str) -> Callable[[str], int]:
    """An integer in low..high; ``what`` names it in the message."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{what} must be in {low}..{high}, got {value}")
        return value

    return parse


def int_at_least(minimum: int, what: str) -> Callable[[str], int]:
    """An integer ≥ minimum; ``what`` names it in the message."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{what} must be at least {minimum}, got {value}")
        return value

    return parse


def comma_separated(kind: type[T], in_range: Callable[[T], bool], plural: str, each: str,
                    unit: str = "") -> Callable[[str], list[T]]:
    """A non-empty comma-separated list of ``kind`` (int or float), each passing ``in_range``.
    The messages: "PLURAL must be comma-separated …, got 'TEXT'" when an item does not parse,
    "each EACH, got 'TEXT'" when one is out of range (``each`` says the range)."""
    noun = ("integers" if kind is int else "numbers") + (f" in {unit}" if unit else "")

    def parse(text: str) -> list[T]:
        try:
            values = [kind(part) for part in text.split(",") if part.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"{plural} must be comma-separated {noun}, got {text!r}") from None
        if not values or not all(in_range(v) for v in values):
            raise argparse.ArgumentTypeError(f"each {each}, got {text!r}")
        return values

    return parse
