"""The statistics poller behind /metrics."""

from __future__ import annotations

import numpy as np

from burrforce.server.api.metrics import LoopStats
from burrforce.server.hotloop.dispatch import Dispatcher
from burrforce.server.hotloop.spec import SessionSpec, build_session


def test_tick_histogram_follows_a_new_session_under_a_reused_id():
    """A session replaced under the same id (a reset, a new bone) starts a new tick epoch:
    the poller counts its ticks from zero instead of subtracting the old session's count."""
    dispatcher = Dispatcher()
    stats = LoopStats(lambda since: dispatcher.snapshot(None, since))

    def add(n_ticks: int) -> None:
        session = build_session(SessionSpec(7, "phantom:workpiece", 0.5))
        session.tick_ns[:] = 50_000  # 50 µs each
        session.ticks_timed = n_ticks
        dispatcher.sessions[7] = session

    add(300)
    stats.poll()
    assert stats.histograms[7].counts.sum() == 300
    add(100)  # fewer ticks than the old session had: must not look like none
    stats.poll()
    assert stats.histograms[7].counts.sum() == 100 and stats.ticks_lost == 0
    dispatcher.sessions[7].ticks_timed = 250
    stats.poll()
    assert stats.histograms[7].counts.sum() == 250
    assert np.isclose(stats.histograms[7].sum_us, 250 * 50.0)
