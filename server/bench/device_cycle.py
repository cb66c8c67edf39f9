"""The device loop's CPU work per cycle, without sockets or a device: map a reading, encode
and tag the POSE, verify and decode a REPLY (made beforehand), take its coupling model,
render, map the force back — what ``devices.loop`` does each cycle besides its I/O.

``python -m burrforce.server.bench.device_cycle N`` runs N cycles after a warm-up of 200 and
prints µs per cycle; ``burrforce bench device --callgrind`` runs it under
``valgrind --tool=callgrind`` for two values of N and reports the difference in instructions
per cycle (repeatable on a busy machine, unlike the time).
"""

from __future__ import annotations

import sys
import time

import numpy as np

from ...client.udp import SessionRules
from ...proto.codec import encode_reply
from ...proto.frames import Transform, frame
from ...proto.messages import Reply
from ...proto.tag import Tagger
from ..devices.mapping import WorkspaceMap
from ..devices.render import CouplingRenderer
from ..haptics.profiles import PROFILES

WARM_UP = 200
KEY = bytes.fromhex("5a" * 32)


class CycleWork:
    """``n`` cycles' worth of replies, made up front (the server's work is not counted)."""

    def __init__(self, n: int) -> None:
        self.rules = SessionRules(1, KEY, 1)
        self.transform = Transform(frame("si_mm"))
        self.mapping = WorkspaceMap((13.0, 0.0, 3.0))
        self.renderer = CouplingRenderer(PROFILES["falcon"])
        self.renderer.warm_up()
        self.axes = np.eye(3)
        tagger = Tagger(KEY)
        self.replies = [encode_reply(self._reply(i), tagger) for i in range(WARM_UP + n)]

    def _reading(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return np.array([0.1 * i % 3.0, 0.0, -1.0]), np.array([5.0, 0.0, 0.0])

    def _reply(self, i: int) -> Reply:
        x = self.mapping.point(self.axes @ self._reading(i)[0])
        t_us = 1_000_000 + i * 1000
        return Reply(1, i + 1, t_us, t_us + 100, t_us + 150, 0, 3, (0.1, 0.2, 0.3),
                     (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1.0, 0.5, 1000.0, (0.0, 0.0, 1.0),
                     tuple(x), (5.0, 0.0, 0.0), 2.0, 0.01, 0.001, 7, (5.0, 0.0, 0.0), None)

    def cycle(self, i: int) -> np.ndarray:
        position, velocity = self._reading(i)
        x = self.mapping.point(self.axes @ position)
        v = self.mapping.vector(self.axes @ velocity)
        t_us = 1_000_000 + i * 1000
        self.rules.datagram(self.transform.point_out(tuple(x)), (0.0, 0.0, 0.0, 1.0), 60000.0,
                            True, None, 0, t_us)
        r = self.rules.accept(self.replies[i], t_us + 300).reply
        tr = self.transform
        self.renderer.accept(r.t_client_us * 1e-6, (t_us + 300) * 1e-6,
                             tr.point_in(r.proxy_position), tr.vector_in(r.proxy_velocity),
                             r.coupling_stiffness, r.coupling_damping, tr.direction_in(r.force))
        f = self.renderer.render(x, v, (t_us + 400) * 1e-6)
        return self.axes.T @ self.mapping.force_to_device(f)

    def run(self, n: int) -> float:
        """µs per cycle over cycles WARM_UP … WARM_UP + n."""
        for i in range(WARM_UP):
            self.cycle(i)
        t0 = time.perf_counter()
        for i in range(WARM_UP, WARM_UP + n):
            self.cycle(i)
        return (time.perf_counter() - t0) / max(n, 1) * 1e6


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
    print(f"{CycleWork(n).run(n):.2f}")
