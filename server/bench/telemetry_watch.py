"""A live view's load on the server, without the browser: sample one session's telemetry at
a rate and encode each sample as the WebSocket does (``python -m
burrforce.server.bench.telemetry_watch DIR SESSION HZ``; prints its sample count at SIGTERM).
``bench latency`` runs it beside the hot loop, paused and resumed between chunks, to compare
round trips with and without someone watching."""

from __future__ import annotations

import json
import signal
import sys
import time
from dataclasses import asdict

from ..api.telemetry import TelemetryReader


def main(argv: list[str]) -> int:
    directory, session, hz = argv[0], int(argv[1]), float(argv[2])
    reader = TelemetryReader(directory)
    period = 1.0 / hz
    samples = 0
    running = True

    def stop(*_: object) -> None:
        nonlocal running
        running = False

    signal.signal(signal.SIGTERM, stop)
    print("ready", flush=True)
    due = time.monotonic()
    while running:
        sample = reader.sample(session)
        if sample is not None:
            json.dumps(asdict(sample))
            samples += 1
        # Paused (SIGSTOP) and resumed, it goes on at its rate instead of catching up.
        due = max(due + period, time.monotonic())
        time.sleep(max(0.0, due - time.monotonic()))
    print(samples, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
