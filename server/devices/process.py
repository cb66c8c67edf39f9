"""The device loop's process, seen from the server: start, status, stop.

The loop runs in a spawned process (not a thread of the control plane: uvicorn and the REST
handlers would take the GIL from the servo cycle; not forked: the parent has threads). It
shares one statistics array (``devices.stats``) and sends one-line events over a queue.
"""

from __future__ import annotations

import collections
import multiprocessing as mp
import os
import queue
import threading
import time

import numpy as np

from . import stats as st
from .loop import DeviceLoopConfig, run

_ENV_LOCK = threading.Lock()
#: How long stop() waits for the loop to zero its device and exit before killing it.
STOP_TIMEOUT_S = 5.0


class DeviceProcess:
    """One device loop. ``start()`` returns at once; ``status()`` reports what it does."""

    def __init__(self, config: DeviceLoopConfig) -> None:
        self.config = config
        ctx = mp.get_context("spawn")
        self._raw = ctx.RawArray("d", st.N_SLOTS)
        self.stats = np.frombuffer(self._raw, dtype=np.float64)
        self._events = ctx.Queue()
        self._process = ctx.Process(target=run, args=(config, self._raw, self._events),
                                    name="burrforce-device", daemon=True)
        self.events: collections.deque[tuple[float, str]] = collections.deque(maxlen=50)
        #: Events received so far (``events`` keeps the last 50): a reader that must see
        #: every one (serve's console) keeps its own count (:meth:`events_since`).
        self.event_count = 0
        #: How many events a console has shown (``burrforce serve``).
        self.console_seen = 0
        self._events_lock = threading.Lock()
        self.started_s: float | None = None

    def start(self, env: dict[str, str] | None = None) -> None:
        """Start the loop's process; ``env`` replaces its environment (e.g. an emulated USB
        device's LD_PRELOAD, which must be there when the process starts)."""
        if env is None:
            self._process.start()
        else:
            with _ENV_LOCK:  # spawn passes os.environ to the new interpreter
                saved = dict(os.environ)
                try:
                    os.environ.clear()
                    os.environ.update(env)
                    self._process.start()
                finally:
                    os.environ.clear()
                    os.environ.update(saved)
        self.started_s = time.time()

    def is_alive(self) -> bool:
        return self._process.is_alive()

    def drain_events(self) -> list[str]:
        """Events that arrived since any reader last drained (also kept in ``events``)."""
        new = []
        with self._events_lock:
            while True:
                try:
                    text = self._events.get_nowait()
                except (queue.Empty, OSError, ValueError):
                    break
                self.events.append((time.time(), text))
                self.event_count += 1
                new.append(text)
        return new

    def events_since(self, count: int) -> tuple[int, list[str]]:
        """(events received so far, the texts of those after the first ``count``) — for a
        reader that must not miss one whoever else drains."""
        self.drain_events()
        with self._events_lock:
            missed = self.event_count - count
            texts = [text for _, text in list(self.events)[-missed:]] if missed > 0 else []
            return self.event_count, texts

    def wait_state(self, states: tuple[str, ...], timeout_s: float) -> str:
        """Wait until the loop is in one of ``states`` (or has exited); returns the state."""
        deadline = time.monotonic() + timeout_s
        while True:
            state = self.state
            if state in states or not self.is_alive() or time.monotonic() > deadline:
                return state
            time.sleep(0.01)

    @property
    def state(self) -> str:
        s = st.STATES[int(self.stats[st.ST_STATE])]
        if s in ("starting", "homing", "running") and self.started_s is not None \
                and not self.is_alive():
            return "failed"  # the process died without saying so (killed)
        return s

    def status(self) -> dict:
        self.drain_events()
        out = st.summary(self.stats)
        out["state"] = self.state
        c = self.config
        out.update({"device": c.device, "actuator": c.actuator, "session": c.session,
                    "workspace": c.workspace.as_dict(), "rpm": c.rpm, "spindle": c.spindle,
                    "stale_ms": c.stale_s * 1e3, "pid": self._process.pid,
                    "exit_code": self._process.exitcode,
                    "events": [{"t": t, "text": text} for t, text in self.events]})
        return out

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """SIGTERM (the loop zeroes the force and closes), then SIGKILL if it hangs."""
        if self._process.pid is None:
            return
        if self._process.is_alive():
            self._process.terminate()
            self._process.join(timeout_s)
            if self._process.is_alive():
                self._process.kill()
                self._process.join(1.0)
        self.drain_events()
        self._events.close()
