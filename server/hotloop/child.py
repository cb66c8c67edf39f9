"""The hot-loop process's main: ``python -m burrforce.server.hotloop.child FD [BEAT]``.

FD is one end of a socket pair the parent (``handle.HotLoopProcess``) holds the other end of;
BEAT, a datagram socket the loop's heartbeat goes out on. :func:`child_main` reads the config
(``loop_config.HotLoopConfig``; first ``loop_config.STANDBY`` for a spare, which warms up
and waits), builds and warms the sessions, opens the port, reports ready, then runs three
threads: the packets (``loop.serve``, this one), the commands (``commands.serve_commands``)
and the heartbeat. Kernels are compiled (or loaded from numba's cache) and every path of a tick run
once before the port opens, so the first packet is as fast as the thousandth.
"""

from __future__ import annotations

import gc
import os
import signal
import socket
import sys
import threading
from multiprocessing.connection import Connection

from ..haptics.stage import warm_up as warm_haptics
from ..realtime import HOT_LOOP_PRIORITY, enter_realtime, leave_realtime
from .commands import CommandContext, serve_commands
from .dispatch import Dispatcher
from .loop import LOOP_COUNTERS, open_socket, serve
from .loop_config import STANDBY, HotLoopConfig
from .spec import SessionSpec, bone_info, build_session
from .wake import WakeConfig

#: The heartbeat thread takes the loop's lock and beats this often
#: (``HotLoopProcess.heartbeat_age_s``).
HEARTBEAT_INTERVAL_S = 0.1
#: The hot loop's niceness where it may raise its priority (``raise_priority``).
HOT_LOOP_NICE = -10
#: A spare's niceness while it warms (``child_main``): it must not slow the loops serving
#: sessions. Measured on a first start on two cores: the demo's round trips p50 1.4 ms, p99
#: 13 ms while the spare compiled at the loops' priority beside them.
SPARE_WARMING_NICE = 19
#: The bone a spare warms on (``HotLoopProcess.spawn_spare``).
SPARE_BONE = "phantom:workpiece"
SPARE_VOXEL_MM = 0.5


def child_main(conn: Connection, beat: socket.socket | None = None) -> None:
    """The hot-loop process: read the config, build and warm the sessions, open the port,
    report ready, then serve packets (this thread), commands (another thread) and the
    heartbeat on ``beat`` (a third)."""
    # The parent owns Ctrl-C and SIGTERM (a terminal, `timeout` or systemd signal the whole
    # group) and stops the loop through the pipe, after zeroing what it must; were the loop
    # to die of them first, its supervisor would restart it in the middle of a shutdown.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raised = raise_priority()
    try:
        config = conn.recv()
        if config == STANDBY:
            # Warming takes a core for a second (a minute when it compiles, on a first start),
            # beside loops already serving: only at the lowest priority, and back to the
            # loop's before it may take a worker's place. Only where that way back is
            # allowed (it is whenever raising was).
            if raised:
                raise_priority(SPARE_WARMING_NICE)
            _warm_spare()
            if raised:
                raise_priority()
            conn.send(("warm",))
            config = conn.recv()
    except (EOFError, OSError):  # the parent went away before starting us: nothing to say
        return
    try:
        if not isinstance(config, HotLoopConfig):
            raise TypeError("expected a HotLoopConfig")
        dispatcher = Dispatcher()
        for spec in config.sessions:
            dispatcher.add(build_session(spec))
        dispatcher.warm_up()
        # Before the port opens: no datagram of a session on its way back is refused.
        dispatcher.restoring.update(config.restoring)
        for session in dispatcher.sessions.values():
            session.publish_telemetry()
        # Every session may be switched to the coupled output later: no first coupled
        # packet may pay for loading its kernels.
        warm_haptics()
        sock = open_socket(config.host, config.udp_port)
    except (OSError, ValueError) as exc:  # a bad bone or address: the message says it all
        conn.send(("error", exc.strerror if isinstance(exc, OSError) and exc.strerror
                   else str(exc)))
        return
    except Exception as exc:
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    lock = threading.Lock()
    stopping = threading.Event()
    for name in LOOP_COUNTERS:  # counted by the loop; there before the first stats call
        dispatcher.counters.setdefault(name, 0)
    # Everything alive now lives for the process: keep the collector from walking it per
    # packet.
    gc.collect()
    gc.freeze()
    wake = config.wake
    # Measured (``bench sessions --workers 2``, 8 sessions, eight alternated pairs): p99
    # 0.74–0.98 ms against 1.77–3.52 ms at nice -10 when the loops contend for the cores
    # (docs/serving.md, "Real-time scheduling").
    realtime = config.realtime and enter_realtime(HOT_LOOP_PRIORITY)
    if realtime:
        # Polling at a real-time priority would keep every normal task off the loop's core
        # while it polls (a yield hands the core only to real-time peers), and the
        # scheduler now runs the loop the moment a datagram wakes it.
        wake = WakeConfig(0.0, wake.cpu_share)
    host, port = sock.getsockname()[:2]
    conn.send(("ready", host, port,
               {sid: bone_info(s) for sid, s in dispatcher.sessions.items()}))
    # Threads inherit the scheduler: only the loop thread is real-time. The commands build
    # sessions (seconds of work) and must not take a core at that priority.
    commands = threading.Thread(target=_normal_priority(serve_commands, realtime),
                                args=(conn, CommandContext(dispatcher, lock, stopping, sock)),
                                name="burrforce-commands", daemon=True)
    commands.start()
    if beat is not None:
        threading.Thread(target=_normal_priority(_heartbeat, realtime),
                         args=(beat, lock, stopping),
                         name="burrforce-heartbeat", daemon=True).start()
    serve(sock, dispatcher, lock, stopping, wake)
    sock.close()
    commands.join(5.0)


def raise_priority(nice: int = HOT_LOOP_NICE) -> bool:
    """Ask the scheduler to run this process ahead of the control plane and whatever else
    shares the cores (nice ``nice``). Allowed for root, with CAP_SYS_NICE (podman:
    ``cap_add: [SYS_NICE]``) or an ``RLIMIT_NICE`` that permits it (docker/compose.yaml's
    ``ulimits: {nice: 30}``: docker gives added capabilities to root only); elsewhere the loop runs
    at the usual priority. Measured (``bench soak``): with a 100 000/s local flood on two
    cores, the usual priority let the flood's CPU push a session's p99 to 164 ms."""
    try:
        os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (PermissionError, OSError):
        return False
    return True


def _normal_priority(target, realtime: bool):
    """``target`` run in a thread that first leaves the real-time scheduler it inherited
    (keeping the loop's niceness), when ``realtime``."""
    if not realtime:
        return target

    def run(*args) -> None:
        leave_realtime()
        target(*args)

    return run


def _warm_spare() -> None:
    """Everything a first session needs, done before it comes: kernels loaded from the
    cache (or compiled) and run through every path of a tick on a small bone."""
    dispatcher = Dispatcher()
    dispatcher.add(build_session(SessionSpec(bone=SPARE_BONE, voxel_mm=SPARE_VOXEL_MM,
                                             publish=False)))
    dispatcher.warm_up()
    warm_haptics()
    del dispatcher
    gc.collect()


def _heartbeat(beat: socket.socket, lock: threading.Lock, stopping: threading.Event) -> None:
    """Beat while the loop can take its lock between two packets: a tick that never ends
    (or a dead process) is what silences it, not an idle socket."""
    beat.setblocking(False)
    while not stopping.wait(HEARTBEAT_INTERVAL_S):
        with lock:
            pass
        try:
            beat.send(b"\x01")
        except BlockingIOError:  # the parent has not read for a while: it only needs one
            pass
        except OSError:  # the parent is gone; the command thread stops the loop
            return


if __name__ == "__main__":
    beat = (socket.socket(fileno=int(sys.argv[2])) if len(sys.argv) > 2 else None)
    child_main(Connection(int(sys.argv[1])), beat)
