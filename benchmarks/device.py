"""``python -m benchmarks.device [--out benchmarks]``: ``burrforce bench device`` (same flags, same
results) with the USB-emulated Falcon (``support.emulation``: umockdev) in place of a real one,
plus the SIGTERM → zero-force run only the emulator's motor log can time."""

from __future__ import annotations

import argparse
from contextlib import AbstractContextManager
from typing import Any

from burrforce.server.bench import device, runner
from support.emulation import EmulatedUsb, emulation_unavailable_reason


class EmulatedFalcon:
    """``device.FalconSource``: a homed Falcon with its firmware loaded, emulated afresh for
    each run."""

    def unavailable(self) -> str | None:
        return emulation_unavailable_reason()

    def start(self) -> AbstractContextManager[Any]:
        return EmulatedUsb("falcon", firmware_loaded=True, homed=True)


def add_parser(sub: argparse._SubParsersAction) -> None:
    device.add_parser(sub).set_defaults(falcon=EmulatedFalcon())


if __name__ == "__main__":
    raise SystemExit(runner.run_alone(add_parser, "device", prog="python -m benchmarks.device"))
