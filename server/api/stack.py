"""The whole server in one object: hot loops, control plane, statistics, uvicorn.

``burrforce serve`` runs it in the foreground; tests and Python harnesses embed it::

    with ServerStack(ServeConfig(http_port=0, udp_port=0, data_dir=tmp), token) as stack:
        stack.url, stack.udp_address, stack.plane ...
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import uvicorn

from ..hotloop import HotLoopProcess
from .app import create_app
from .config import ServeConfig
from .journal import Journal, resume
from .metrics import LoopStats, PoolStats
from .models import Features, Parameters
from .plane import ControlPlane
from .sessions import ManagedSession
from .sources import BoneSource
from .supervisor import Supervisor
from .workers import start_hot_loops

START_TIMEOUT_S = 600.0
log = logging.getLogger("burrforce.api")


class ServerStack:
    """Hot loops + control plane + REST app (+ an optional default session).

    Args:
        config: server configuration (``http_port=0``/``udp_port=0`` pick free ports;
            ``workers``: how many hot loops, default one).
        token: the REST bearer token.
    """

    def __init__(self, config: ServeConfig, token: str,
                 say: Callable[[str], None] | None = None, journal: bool = True) -> None:
        self.config = config
        self.token = token
        self.say = say
        self.use_journal = journal
        self.journal: Journal | None = None
        #: Sessions ``start_backend`` resumed from the journal.
        self.resumed: list[int] = []
        self.plane: ControlPlane | None = None
        self.stats: LoopStats | None = None
        self.supervisor: Supervisor | None = None
        self.server: uvicorn.Server | None = None
        self._thread: threading.Thread | None = None

    def start_backend(self, spawned: list[HotLoopProcess] | None = None) -> None:
        """The hot loops, the control plane, the statistics poller, the supervisor and the
        journal, after resuming the journaled sessions (no HTTP yet). ``spawned``: the hot
        loops' processes ``hotloop.pool.spawn_pool`` made ahead for this config.

        Raises:
            RuntimeError: a worker's UDP port is taken, or a worker failed to start.
        """
        workers = start_hot_loops(self.config, spawned)
        try:
            self.plane = plane = ControlPlane(self.config, workers)
        except BaseException:
            for hot in workers:
                hot.stop()
            raise
        try:
            # Through the plane: the supervisor replaces a worker after a crash.
            if len(workers) == 1:
                self.stats = LoopStats(lambda since: plane.hot.call("stats",
                                                                    tick_times_since=since))
            else:
                self.stats = LoopStats(PoolStats(lambda: plane.workers))
            plane.work_us_per_s = self.stats.work_us_per_s
            self.stats.poll()
            self.stats.start()
            self.supervisor = Supervisor(plane, self.stats, self.say)
            self.supervisor.start()
            if self.use_journal:
                stats = self.stats
                self.journal = Journal(plane, lambda sid: stats.next_streams().get(sid))
                self.resumed = resume(plane, self.journal, self.say or log.info)
                self.journal.start()
            app = create_app(plane, self.token, self.stats, self.supervisor, self.journal)
            self.server = uvicorn.Server(uvicorn.Config(
                app, host=self.config.host, port=self.config.http_port, log_level="warning",
                access_log=False, timeout_graceful_shutdown=5))
        except BaseException:
            self.stop()
            raise

    def add_session(self, source: BoneSource, parameters: Parameters | None = None,
                    features: Features | None = None, session_id: int | None = None,
                    key_hex: str | None = None, authenticated: bool = True
                    ) -> ManagedSession:
        """Create a session and wait for its bone. Raises ValueError if it fails to load."""
        assert self.plane is not None
        session, job = self.plane.create_session(
            session_id, source, parameters or Parameters(), features or Features(),
            authenticated=authenticated, key_hex=key_hex)
        if not self.plane.wait(job, START_TIMEOUT_S):
            raise TimeoutError(f"loading {source.source} took too long")
        if session.state != "ready":
            raise ValueError(f"cannot load {source.source}: {session.error}")
        return session

    def serve_in_thread(self, timeout_s: float = 30.0) -> None:
        """Serve HTTP from a background thread (tests, harnesses); returns once bound."""
        assert self.server is not None
        self.server.install_signal_handlers = lambda: None  # type: ignore[method-assign]
        self._thread = threading.Thread(target=self.server.run, name="burrforce-http",
                                        daemon=True)
        self._thread.start()
        deadline = time.monotonic() + timeout_s
        while not self.server.started:
            if not self._thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError("the REST server did not start (is the port free?)")
            time.sleep(0.01)

    @property
    def http_port(self) -> int:
        assert self.server is not None and self.server.started
        return self.server.servers[0].sockets[0].getsockname()[1]

    @property
    def url(self) -> str:
        host = self.config.host
        if host in ("0.0.0.0", "::"):
            host = "127.0.0.1"
        elif ":" in host:
            host = f"[{host}]"
        return f"http://{host}:{self.http_port}"

    @property
    def hot(self) -> HotLoopProcess | None:
        """The running hot loop of worker 0 (a new one after a restart)."""
        return self.plane.hot if self.plane is not None else None

    @property
    def workers(self) -> list[HotLoopProcess]:
        """The running hot loops, worker i at index i."""
        return list(self.plane.workers) if self.plane is not None else []

    @property
    def udp_address(self) -> tuple[str, int]:
        """Worker 0's UDP endpoint (a session's own: ``plane.address(session)``)."""
        assert self.hot is not None and self.hot.address is not None
        return self.hot.address

    def stop(self) -> None:
        """Stop HTTP, recordings, sessions and the hot loop; remove the shared bones."""
        if self.server is not None:
            self.server.should_exit = True
        if self._thread is not None:
            self._thread.join(10.0)
            self._thread = None
        if self.supervisor is not None:  # first: stopping the loop is not a crash
            self.supervisor.stop()
        if self.journal is not None:  # a last pass, while the sessions are still there
            self.journal.stop()
        if self.stats is not None:
            self.stats.stop()
        if self.plane is not None:
            self.plane.close()
            for hot in self.plane.workers:
                hot.stop()

    def __enter__(self) -> ServerStack:
        if self.plane is None:
            self.start_backend()
            self.serve_in_thread()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
