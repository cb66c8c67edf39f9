"""The hot loop's command table: what the parent may ask of a running loop, one handler each.

A thread in the loop process (``child``) reads ``(name, kwargs)`` from the pipe, finds the
handler in :data:`COMMANDS` and answers ``("ok", result)``; a handler that raises is answered
``("error", (kind, message))``, the kind being what ``errors.classify`` makes of the exception
(``KeyError``: ``not_found``, ``SessionExists``: ``conflict``, ``ValueError`` and ``TypeError``:
``invalid``, anything else: ``internal``). The handle (``handle.HotLoopProcess.call``) turns
that back into an ``errors.CommandError``.

Handlers change sessions between two packets, under the loop's lock; the slow parts (building
a session, finding forbidden bricks, closing a recording) run outside it. Nothing here runs
per packet.
"""

from __future__ import annotations

import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from .. import compile_cache
from ..bone import MaterialTable, ShaftParams
from ..bone.engine import BoneEngine, check_burr, tick_warmed
from ..model.params import CuttingParams
from .dispatch import Dispatcher
from .errors import CommandError, SessionExists, classify
from .session import Session
from .session_config import SessionConfig
from .spec import SessionSpec, bone_info, build_session

#: The longest the packet thread waits for the GIL while a session is built, s (about).
GIL_TURN_S = 100e-6
#: The longest a tool change waits for a ``burrforce compile`` filling the cache, s: it
#: compiles the tick itself after that, and answers well within the control plane's wait
#: for a slow command (``handle.START_TIMEOUT_S``).
FILLER_WAIT_S = 300.0


@dataclass(frozen=True)
class CommandContext:
    """What a command acts on: the loop's sessions (``dispatcher``), the lock the packet
    thread holds while it handles a packet, the event that ends the loop, and its socket."""

    dispatcher: Dispatcher
    lock: threading.Lock
    stopping: threading.Event
    sock: socket.socket


#: A command's handler: the loop and the command's keyword arguments in, a picklable result out.
Handler = Callable[[CommandContext, dict], object]


def serve_commands(conn: Connection, ctx: CommandContext) -> None:
    """Answer the parent's commands on ``conn`` until ``stop`` (or the parent going away,
    which means the same: the loop does not outlive it)."""
    while True:
        try:
            command, kwargs = conn.recv()
        except (EOFError, OSError):  # the parent is gone: do not outlive it
            command, kwargs = "stop", {}
        except Exception as exc:  # an unpicklable command
            _send(conn, "error", CommandError("invalid", f"bad command: {exc}").as_data())
            continue
        try:
            result = run_command(ctx, command, kwargs)
        except Exception as exc:
            _send(conn, "error", classify(exc).as_data())
        else:
            _send(conn, "ok", result)
        if ctx.stopping.is_set():  # set by ``stop`` only
            return


def run_command(ctx: CommandContext, command: str, kwargs: dict) -> object:
    """The result of ``command`` with ``kwargs``.

    Raises:
        ValueError: no such command; else whatever its handler raised.
    """
    handler = COMMANDS.get(command) if isinstance(command, str) else None
    if handler is None:
        raise ValueError(f"unknown command {command!r}")
    return handler(ctx, kwargs)


def _stop(ctx: CommandContext, kwargs: dict) -> None:
    ctx.stopping.set()
    try:
        ctx.sock.shutdown(socket.SHUT_RDWR)  # wakes the blocking recvfrom
    except OSError:
        pass


def _stats(ctx: CommandContext, kwargs: dict) -> object:
    return ctx.dispatcher.snapshot(ctx.lock, kwargs.get("tick_times_since"))


def _session_state(ctx: CommandContext, kwargs: dict) -> dict:
    with ctx.lock:
        session = _session(ctx.dispatcher, kwargs["session_id"])
        n = int(kwargs.get("max_events", 100))
        engine = session.engine
        events = engine.tally.latest(n, engine.materials.name_of) if n > 0 else []
        stats = session.stats()
        stats["haptics"] = session.haptics.snapshot()
        # When the counters were read, on the loop's clock: a rate from two states is then
        # the loop's own, not skewed by how long each request took to come back.
        stats["t_loop_s"] = time.monotonic()
    stats.pop("tick_times_us")
    stats["events"] = [e.__dict__ for e in events]
    return stats


def _add_session(ctx: CommandContext, kwargs: dict) -> dict:
    return _install_session(ctx, kwargs["spec"], adding=True)


def _replace_session(ctx: CommandContext, kwargs: dict) -> dict:
    return _install_session(ctx, kwargs["spec"], adding=False)


def _install_session(ctx: CommandContext, spec: object, adding: bool) -> dict:
    """Build the session ``spec`` describes and add it (or replace the one with its id);
    its bone's ``spec.bone_info``."""
    if not isinstance(spec, SessionSpec):
        raise TypeError("spec must be a SessionSpec")
    dispatcher, lock = ctx.dispatcher, ctx.lock
    with lock:
        if adding and spec.session_id in dispatcher.sessions:
            raise SessionExists(f"session {spec.session_id} exists")
    # Loading and warming are the slow part: on a dispatcher of its own, outside the lock;
    # the session goes in (or replaces the old one) between two packets.
    if not tick_warmed(spec.params):
        compile_cache.wait_for_filler(FILLER_WAIT_S)  # as a tool change (_warm_tick)
    with _short_gil_turns():
        session = build_session(spec)
        probe = Dispatcher()
        probe.add(session)
        probe.warm_up()
    old = None
    with lock:
        if adding:
            dispatcher.add(session)
        else:
            old = _session(dispatcher, spec.session_id)
            # Stream numbers go on from the old session's: one it offered is never
            # offered again (a captured hello and POSE would open it; SPEC 5.2).
            session.next_stream = old.next_stream
            dispatcher.sessions[spec.session_id] = session
        session.publish_telemetry()
    # The old bone is unmapped here, with the packet thread free to take the lock.
    del old
    return bone_info(session)


def _configure(ctx: CommandContext, kwargs: dict) -> None:
    config = kwargs["config"]
    if not isinstance(config, SessionConfig):
        raise TypeError("config must be a SessionConfig")
    with ctx.lock:
        _session(ctx.dispatcher, kwargs["session_id"]).configure(config)


def _set_engine(ctx: CommandContext, kwargs: dict) -> None:
    _change_engine(ctx, **kwargs)


def _change_engine(ctx: CommandContext, session_id: int, params: CuttingParams | None = None,
                   shaft: ShaftParams | None = None, materials: MaterialTable | None = None,
                   publish: bool | None = None) -> None:
    """Change a session's burr, shaft, materials or shared-memory publishing between two
    packets. Everything is checked before anything changes; the stream goes on.

    A material table with other forbidden flags needs new forbidden bricks: they are found
    here, outside the loop's lock (a pass over a shared bone's bricks, or the voxels of a
    private one; either kernel releases the GIL), not in the next tick."""
    dispatcher, lock = ctx.dispatcher, ctx.lock
    with lock:
        engine = _session(dispatcher, session_id).engine
        grid, current = engine.grid, engine.materials
    bricks = None
    if materials is not None and not np.array_equal(materials.forbidden, current.forbidden):
        bricks = engine.forbidden_bricks_for(materials)
    if params is not None and not tick_warmed(params):
        _warm_tick(engine, params)
    with lock:
        session = _session(dispatcher, session_id)
        engine = session.engine
        if engine.grid is not grid:
            raise RuntimeError("the session's bone changed meanwhile; try again")
        new_shaft = shaft if shaft is not None else engine.shaft
        new_params = params if params is not None else engine.params
        check_burr(grid.spacing_mm, new_params, new_shaft)
        changed = new_shaft != engine.shaft or new_params != engine.params
        if new_shaft != engine.shaft:
            engine.shaft = new_shaft
        if new_params != engine.params:
            engine.params = new_params  # resets the coverage cache and the carve memory
        if changed:
            session.engine_changed()  # the hot path's copies (the coupling's shaft radius too)
        if materials is not None:
            engine.set_materials(materials, bricks)
        if publish is not None:
            session.publish_bone(publish)


def _warm_tick(engine: BoneEngine, params: CuttingParams) -> None:
    """Load (or compile) the tick ``params``' burr needs, outside the loop's lock, before
    the burr changes: the tick that follows must not. After a first start only the round
    burr's was warmed; a ``burrforce compile`` filling the cache behind the server is waited
    for, so the tick loads from the cache rather than compiling here a second time."""
    compile_cache.wait_for_filler(FILLER_WAIT_S)
    with _short_gil_turns():
        # An engine of its own on the same bone: the same types, its own scratch buffers.
        BoneEngine(engine.grid, engine.materials, params, engine.shaft).warm_up(False)


def _start_recording(ctx: CommandContext, kwargs: dict) -> dict:
    return _attach_recorder(ctx, **kwargs)


def _attach_recorder(ctx: CommandContext, session_id: int, path: str, snapshot_version: int,
                     bone_name: str = "", max_bytes: int = 2 << 30) -> dict:
    """Attach a recorder between two packets (``record.start_recording``). The control plane
    has written the start snapshot at ``snapshot_version``; the bricks carved since then are
    saved here, under the lock, as the recording's start patch."""
    # Imported at the first recording, not with the loop (no cycle: ``record`` is below
    # ``hotloop``): the recorder and the replay beside it would add ~0.2 s to every loop's
    # start (measured on two busy cores), and most loops never record.
    from ..record.recorder import start_recording

    with ctx.lock:
        session = _session(ctx.dispatcher, session_id)
        start_recording(session, path, bone_name=bone_name, max_bytes=max_bytes,
                        snapshot_version=snapshot_version)
        return {"start_version": session.engine.grid.version}


def _stop_recording(ctx: CommandContext, kwargs: dict) -> object:
    with ctx.lock:
        recorder = _session(ctx.dispatcher, kwargs["session_id"]).recorder
        if recorder is not None:
            recorder.detach()
    # Closing writes the last chunk: outside the lock, the loop goes on meanwhile.
    return recorder.close() if recorder is not None else None


def _recording_status(ctx: CommandContext, kwargs: dict) -> object:
    with ctx.lock:
        recorder = _session(ctx.dispatcher, kwargs["session_id"]).recorder
    return recorder.status() if recorder is not None else None


def _remove_session(ctx: CommandContext, kwargs: dict) -> bool:
    with ctx.lock:
        ctx.dispatcher.restoring.discard(kwargs["session_id"])
        return ctx.dispatcher.sessions.pop(kwargs["session_id"], None) is not None


def _restored(ctx: CommandContext, kwargs: dict) -> None:
    """The restore after a restart is over: a session not added back by now is gone, and
    its datagrams are answered UNKNOWN_SESSION."""
    with ctx.lock:
        ctx.dispatcher.restoring.clear()


def _restart_stream(ctx: CommandContext, kwargs: dict) -> None:
    with ctx.lock:
        ctx.dispatcher.sessions[kwargs["session_id"]].end_stream()


#: Every command a loop answers, by name.
COMMANDS: dict[str, Handler] = {
    "stop": _stop,
    "stats": _stats,
    "session_state": _session_state,
    "add_session": _add_session,
    "replace_session": _replace_session,
    "configure": _configure,
    "set_engine": _set_engine,
    "start_recording": _start_recording,
    "stop_recording": _stop_recording,
    "recording_status": _recording_status,
    "remove_session": _remove_session,
    "restart_stream": _restart_stream,
    "restored": _restored,
}


@contextmanager
def _short_gil_turns(interval_s: float = GIL_TURN_S) -> Iterator[None]:
    """While the command thread builds a session, the packet thread waits at most about
    ``interval_s`` for the GIL (the interpreter's default turn is 5 ms).

    What is left of a build is milliseconds of plain Python (objects, small arrays: the
    voxel work comes precomputed in a shared bone's file), in stretches up to ~0.5 ms
    (measured with ``benchmarks.gil_probe``). A packet arriving meanwhile would wait for the
    stretch to end, up to a whole turn; shorter turns bound that wait instead."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def _session(dispatcher: Dispatcher, session_id: int) -> Session:
    try:
        return dispatcher.sessions[session_id]
    except KeyError:
        raise KeyError(f"no session {session_id}") from None


def _send(conn: Connection, status: str, result: object) -> None:
    try:
        conn.send((status, result))
    except (OSError, EOFError):
        pass
    except Exception as exc:  # an unpicklable result must not end the command thread
        try:
            conn.send(("error", CommandError(
                "internal", f"the result could not be sent: {exc}").as_data()))
        except Exception:
            pass
