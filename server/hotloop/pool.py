"""A pool of hot loops: how many the cores allow, their UDP ports, and starting them side by side.

``burrforce serve --workers N`` runs N loop processes (``handle.HotLoopProcess``), worker i on
``udp_port + i``; this room decides the count (``default_workers``), checks the ports before
anything starts (``check_ports_free``) and starts them together (``start_pool``). Placing
sessions on the workers is the control plane's.
"""

from __future__ import annotations

import math
import os
import socket
import threading
from pathlib import Path

from .handle import START_TIMEOUT_S, HotLoopProcess
from .loop_config import HotLoopConfig
from .wake import DEFAULT_WAKE, WakeConfig


def usable_cores(cpu_max: str = "/sys/fs/cgroup/cpu.max") -> int:
    """Cores this process may keep busy: the CPUs it may run on, capped by a cgroup v2 CPU
    quota (``docker run --cpus 2``, a Kubernetes limit), which the affinity mask does not
    show: 32 host CPUs under a 2-core quota are 2."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota, period = Path(cpu_max).read_text().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, math.ceil(int(quota) / int(period))))
    except (OSError, ValueError):  # no cgroup v2 here, or unreadable: the affinity decides
        pass
    return cores


def default_workers() -> int:
    """Hot loops ``burrforce serve`` starts when not told: one per usable core, less one for
    the control plane (uvicorn, loads, the journal), at least one."""
    return max(1, usable_cores() - 1)


def worker_ports(udp_port: int, workers: int) -> list[int]:
    """Worker i's UDP port: ``udp_port + i`` (0: each takes an ephemeral one)."""
    return [0 if udp_port == 0 else udp_port + i for i in range(workers)]


def check_ports_free(host: str, udp_port: int, workers: int) -> None:
    """Fail before anything starts if a worker's port is taken (or past 65535): a pool that
    came up with a hole in its range would answer on ports nobody configured.

    Raises:
        RuntimeError: which port, which worker, and why.
    """
    if udp_port == 0:
        return
    last = udp_port + workers - 1
    if last > 65535:
        raise RuntimeError(f"{workers} workers need UDP ports {udp_port}..{last}: past 65535 "
                           "(lower --udp-port or --workers)")
    for i, port in enumerate(worker_ports(udp_port, workers)):
        try:
            family, kind, proto, _, address = socket.getaddrinfo(
                host, port, type=socket.SOCK_DGRAM)[0]
            with socket.socket(family, kind, proto) as probe:
                probe.bind(address)
        except OSError as exc:
            raise RuntimeError(
                f"UDP port {port} (worker {i} of {workers}: --udp-port {udp_port} + {i}) "
                f"cannot be bound on {host}: {exc.strerror or exc}") from None


def spawn_pool(host: str, udp_port: int, workers: int, wake: WakeConfig = DEFAULT_WAKE,
               realtime: bool = False, warm: bool = False) -> list[HotLoopProcess]:
    """The pool's processes spawned, their ports checked, not yet started: each interpreter
    imports while the caller goes on (``serve`` imports its web stack meanwhile: on two cores
    the two start-ups overlap instead of following each other). :func:`start_pool` starts
    them; a caller that gives up first kills them (or exits: they end with their pipe).
    ``warm``: also send each its config, so that it warms up and opens its port meanwhile
    too (only where the kernels are all in the cache: else each would compile them, beside
    the compile a first start runs).

    Raises:
        ValueError: ``workers`` < 1.
        RuntimeError: a port is taken (nothing is spawned).
    """
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    check_ports_free(host, udp_port, workers)
    pool = [HotLoopProcess(HotLoopConfig(host, port, (), wake, realtime))
            for port in worker_ports(udp_port, workers)]
    try:
        for hot in pool:
            hot.spawn()
            if warm:
                # Each loop loads its kernels and opens its port while the caller is still
                # importing (~0.5 s of a warm start); start_pool collects their "ready".
                hot.send_config()
    except BaseException:
        for hot in pool:
            hot.kill()
        raise
    return pool


def start_pool(host: str, udp_port: int, workers: int,
               timeout_s: float = START_TIMEOUT_S,
               wake: WakeConfig = DEFAULT_WAKE, realtime: bool = False,
               spawned: list[HotLoopProcess] | None = None) -> list[HotLoopProcess]:
    """Start ``workers`` hot loops with no sessions, worker i on ``udp_port + i`` (or an
    ephemeral port each when ``udp_port`` is 0), each waking ahead as ``wake`` says, and
    asking for the real-time scheduler with ``realtime``. The interpreters start and warm up
    side by side, not one after the other. ``spawned``: the processes :func:`spawn_pool`
    made for these arguments, started instead of spawning new ones.

    Raises:
        ValueError: ``workers`` < 1, or ``spawned`` is not that many.
        RuntimeError: a port is taken or a worker failed to start (every worker is stopped).
    """
    if spawned is not None and len(spawned) != workers:
        raise ValueError(f"{len(spawned)} spawned hot loops for {workers} workers")
    pool = spawned if spawned is not None else spawn_pool(host, udp_port, workers, wake,
                                                          realtime)
    errors: list[str] = []

    def start(i: int) -> None:
        try:
            pool[i].start(timeout_s)
        except RuntimeError as exc:
            errors.append(f"worker {i}: {exc}" if workers > 1 else str(exc))

    try:
        threads = [threading.Thread(target=start, args=(i,), daemon=True)
                   for i in range(workers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    except BaseException:
        for hot in pool:
            hot.kill()
        raise
    if errors:
        for hot in pool:
            hot.stop()
        raise RuntimeError("; ".join(sorted(errors)))
    return pool
