"""Waking ahead of a stream's packets (``hotloop.wake``): the prediction, the polling window,
the CPU budget, on synthetic clocks; then a real hot loop on loopback that polls for a 1 kHz
stream and answers every packet, and one that does not."""

from __future__ import annotations

import select
import socket
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_profiles import examples

from burrforce.client.udp import BurrClient
from burrforce.proto.tag import new_key
from burrforce.server.hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec
from burrforce.server.hotloop.loop import _poll_ahead
from burrforce.server.hotloop.wake import (
    BACKOFF_MAX_S,
    BACKOFF_S,
    BUDGET_CAP_S,
    PERIOD_MAX_S,
    PREEMPT_BURST,
    WAKE_COUNTERS,
    RunnableTasks,
    WakeAhead,
    WakeConfig,
)

MS = 1_000_000  # ns
S = 1_000_000_000


def _wake(lead_us: float = 250.0, share: float = 0.4, runnable=lambda: 1) -> WakeAhead:
    """A WakeAhead at t = 0 on a 2-core machine where only the loop runs (by default)."""
    return WakeAhead(WakeConfig(lead_us, share), 0, {}, 2, runnable)


def _streamed(wake: WakeAhead, key: object, start_ns: int, period_ns: int, n: int) -> int:
    """``n`` arrivals of ``key`` every ``period_ns`` from ``start_ns``, each waking the loop
    from sleep; the last one's time."""
    t = start_ns
    for i in range(n):
        t = start_ns + i * period_ns
        wake.woke(t)
        wake.arrived(key, t)
    return t


def test_a_steady_stream_gets_a_window_around_its_next_packet():
    wake = _wake()
    assert wake.next_poll(0) is None  # nothing predicted yet
    last = _streamed(wake, "a", 10 * MS, MS, 20)
    window = wake.next_poll(last + 100_000)
    assert window == (last + MS - 250_000, last + MS + 250_000)


def test_the_earliest_stream_decides_and_a_window_that_passed_is_dropped():
    wake = _wake(200.0, 1.0)
    a = _streamed(wake, "a", 10 * MS, MS, 10)
    b = _streamed(wake, "b", 10 * MS + 400_000, MS, 10)
    assert wake.next_poll(b + 1000) == (a + MS - 200_000, a + MS + 200_000)
    # a's packet never came: past its window, b's is next, and a counts as missed.
    assert wake.next_poll(a + MS + 200_001) == (b + MS - 200_000, b + MS + 200_000)
    assert wake.counters["wake_missed"] == 1
    wake.forget("b")
    assert wake.next_poll(a + MS + 200_002) is None


def test_a_pause_or_a_burst_is_not_a_period():
    wake = _wake()
    last = _streamed(wake, "a", 0, MS, 5)
    wake.arrived("a", last + int(PERIOD_MAX_S * 1e9) + 1)  # a pause
    assert wake.next_poll(last + int(PERIOD_MAX_S * 1e9) + 2) is None
    t = last + int(PERIOD_MAX_S * 1e9) + 1
    wake.arrived("a", t + 50_000)  # a burst: 50 µs apart
    assert wake.next_poll(t + 60_000) is None
    assert wake.counters["wake_irregular"] == 2  # each one counted: it was not polled for


def test_the_period_follows_the_stream():
    wake = _wake(100.0, 1.0)
    last = _streamed(wake, "a", 0, MS, 50)
    last = _streamed(wake, "a", last + 2 * MS, 2 * MS, 60)  # now 500 Hz
    start, end = wake.next_poll(last)
    assert abs((start + end) // 2 - (last + 2 * MS)) < 1000


def test_a_loop_awake_beyond_its_share_stops_polling_until_it_has_slept():
    wake = _wake(300.0, 0.4)
    t = _streamed(wake, "a", 0, MS, 5)
    wake.woke(t)
    # Awake (working) for 30 packets straight: far more than 40 % of the time.
    for _ in range(30):
        t += MS
        wake.arrived("a", t)
    assert wake.next_poll(t + 1000) is None
    assert wake.counters["wake_starved"] == 1
    # Then asleep for 60 ms: the budget is back.
    wake.woke(t + 60 * MS)
    t = _streamed(wake, "a", t + 60 * MS, MS, 2)
    assert wake.next_poll(t + 1000) == (t + MS - 300_000, t + MS + 300_000)


def test_no_polling_while_every_core_is_taken():
    running = [3]  # the loop and two others on two cores
    wake = _wake(runnable=lambda: running[0])
    t = _streamed(wake, "a", 0, MS, 20)
    assert wake.next_poll(t + 1000) is None
    assert wake.counters["wake_busy"] == 1
    running[0] = 2  # a core is free again
    assert wake.next_poll(t + 2000) == (t + MS - 250_000, t + MS + 250_000)
    assert _wake(runnable=lambda: None).next_poll(0) is None  # (nothing predicted yet)
    unknown = _wake(runnable=lambda: None)
    t = _streamed(unknown, "a", 0, MS, 20)
    assert unknown.next_poll(t + 1000) is not None  # no procfs: the share alone decides


def _quiet_s(wake: WakeAhead, t: int) -> tuple[int, int]:
    """Stream at 1 kHz until the loop polls again; (seconds it did not, the time then)."""
    start = t
    while True:
        t = _streamed(wake, "a", t + MS, MS, 2)
        if wake.next_poll(t + 1000) is not None:
            return round((t - start) / S), t


def test_a_task_holding_the_core_stops_polling_for_a_growing_while():
    wake = _wake(share=1.0)
    t = _streamed(wake, "a", 0, MS, 20)
    wake.preempted(t)  # a task that ran once or twice: only those windows end
    wake.preempted(t)
    assert wake.next_poll(t + 1000) is not None
    wake.preempted(t)  # it keeps happening: back off
    quiet, t = _quiet_s(wake, t)
    backoffs = [quiet]
    slow = []
    for _ in range(5):  # it holds the core at every try: a few windows, then a longer pause
        n = 0
        while wake.next_poll(t + 1000) is not None:
            wake.preempted(t)
            n += 1
            t = _streamed(wake, "a", t + MS, MS, 1)
        slow.append(n)
        quiet, t = _quiet_s(wake, t)
        backoffs.append(quiet)
    assert backoffs == [1, 2, 4, 8, 16, 16]
    assert all(1 <= n <= 1 + PREEMPT_BURST for n in slow), slow
    assert wake.counters["wake_quiet"] > 20_000  # one a call while quiet
    # After a quiet spell longer than twice the back-off, it starts again from BACKOFF_S.
    t = _streamed(wake, "a", t + int(3 * BACKOFF_MAX_S * S), MS, 2)
    for _ in range(3):
        wake.preempted(t)
    assert _quiet_s(wake, t)[0] == BACKOFF_S


def test_the_counters_are_kept_in_the_given_dict():
    counters = {"received": 5}
    wake = WakeAhead(WakeConfig(), 0, counters, 2, lambda: 1)
    assert set(WAKE_COUNTERS) <= set(counters) and counters["received"] == 5
    t = _streamed(wake, "a", 0, MS, 20)
    start, _ = wake.next_poll(t + 1000)
    wake.polled(start, start + 3 * MS // 2, True)
    assert counters["wake_caught"] == 1 and counters["wake_poll_ms"] == 1


def test_a_datagram_before_the_window_wakes_the_loop_and_counts_as_early():
    wake = _wake()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx, select.epoll() as poller:
        rx.bind(("127.0.0.1", 0))
        poller.register(rx.fileno(), select.EPOLLIN)
        tx.sendto(b"x", rx.getsockname())
        now = time.monotonic_ns()
        began = time.perf_counter()
        events = _poll_ahead(poller, (now + 2 * S, now + 3 * S), wake, time.monotonic_ns)
        assert time.perf_counter() - began < 1.0  # woken by the datagram, not the window
        assert [fd for fd, _ in events] == [rx.fileno()]
    assert wake.counters["wake_early"] == 1 and wake.counters["wake_caught"] == 0


@pytest.mark.parametrize("text, running", [
    ("0.52 0.58 0.59 2/345 6789\n", 2), ("1.00 1.00 1.00 17/1024 1\n", 17),
    ("garbage\n", None), ("", None)])
def test_runnable_tasks_come_from_loadavg(tmp_path, text, running):
    path = tmp_path / "loadavg"
    path.write_text(text)
    tasks = RunnableTasks(str(path))
    try:
        assert tasks() == running
    finally:
        tasks.close()
    assert RunnableTasks(str(tmp_path / "missing"))() is None
    here = RunnableTasks()
    assert here() is None or here() >= 1  # this process is running
    here.close()


@settings(max_examples=examples(200), deadline=None)
@given(st.lists(st.tuples(st.sampled_from("abc"), st.integers(1, 3 * MS),
                          st.integers(0, 2 * MS)), min_size=1, max_size=200),
       st.floats(0.0, 5000.0), st.floats(0.01, 1.0))
def test_windows_lie_around_a_predicted_packet_and_the_budget_stays_capped(events, lead_us,
                                                                           share):
    """Any arrivals, any awake spans: a window is (due − lead, due + lead) of a stream's
    prediction, never already over, and the budget never exceeds its cap."""
    wake = WakeAhead(WakeConfig(lead_us, share), 0, {}, 2, lambda: 1)
    now = 0
    for key, gap, awake in events:
        now += gap
        wake.arrived(key, now)
        window = wake.next_poll(now + awake)
        if window is not None:
            start, end = window
            assert end - start == 2 * wake.lead_ns
            assert end > now + awake
            assert (start + end) // 2 in wake._due.values()
        assert wake._budget_ns <= BUDGET_CAP_S * 1e9
        wake.woke(now + awake)


@pytest.mark.parametrize("lead, share, words", [
    (-1.0, 0.4, "lead must be within [0, 5000]"),
    (float("nan"), 0.4, "lead must be within"),
    (6000.0, 0.4, "lead must be within"),
    (300.0, 0.0, "CPU share must be within [0.01, 1]"),
    (300.0, 1.5, "CPU share must be within"),
    (300.0, float("inf"), "CPU share must be within"),
])
def test_bad_settings_say_what_is_wrong(lead, share, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        WakeConfig(lead, share)


# -- a real hot loop -----------------------------------------------------------------------

SID = 3
PACKETS = 600


def _stream_at_1khz(address, key: bytes) -> int:
    """PACKETS exchanges at 1 kHz through the client (a peer socket of its own after the
    first); how many were answered."""
    answered = 0
    with BurrClient(*address, session=SID, key=key, timeout_s=0.5) as client:
        due = time.perf_counter()
        for _ in range(PACKETS):
            due += 0.001  # sleep most of the way, spin the rest: a steady 1 kHz, as a device
            ahead = due - time.perf_counter()
            if ahead > 0.0006:
                time.sleep(ahead - 0.0004)
            while time.perf_counter() < due:
                pass
            try:
                client.exchange((30.0, 30.0, 60.0), rpm=0.0)
            except TimeoutError:
                continue
            answered += 1
    return answered


@pytest.mark.parametrize("lead_us", [250.0, 0.0])
def test_a_hot_loop_answers_a_1khz_stream_polling_for_it_or_not(lead_us):
    key = new_key()
    spec = SessionSpec(SID, "phantom:workpiece", 0.5, key, SessionConfig())
    hot = HotLoopProcess(HotLoopConfig(sessions=(spec,), wake=WakeConfig(lead_us=lead_us)))
    address = hot.start()
    try:
        answered = _stream_at_1khz(address, key)
        counters = hot.stats()["counters"]
    finally:
        hot.stop()
    assert answered == PACKETS
    assert counters["replied"] >= PACKETS
    wake = {k: counters[k] for k in WAKE_COUNTERS}
    if lead_us:
        # It predicted the stream: each packet after the first few was polled for, or not
        # for a reason it counted (on a loaded machine the client's own timing makes many
        # early or irregular). Some were caught polling, unless every core was taken the
        # whole time (another suite beside this one): then it rightly never polled, and
        # the client's own timing was as uneven as the machine.
        assert (wake["wake_caught"] > 0
                or wake["wake_busy"] + wake["wake_irregular"] > PACKETS // 2), wake
        assert sum(wake[k] for k in WAKE_COUNTERS if k != "wake_poll_ms") > PACKETS // 2, wake
    else:
        assert not any(wake.values()), wake
