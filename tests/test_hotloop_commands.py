"""The hot loop's command table (``hotloop.commands``), run in this process on real sessions
and a real pipe: the answers for each kind of command, and a handler for every name the server
sends. (``test_hotloop_errors`` runs the same table in a loop process.)"""

from __future__ import annotations

import re
import socket
import threading
from multiprocessing import Pipe
from pathlib import Path

import pytest

from burrforce.server.hotloop import Dispatcher, SessionConfig, SessionSpec, build_session
from burrforce.server.hotloop.commands import (
    COMMANDS,
    CommandContext,
    run_command,
    serve_commands,
)
from burrforce.server.hotloop.errors import SessionExists

SERVER = Path(__file__).resolve().parents[1] / "server"
#: Where the product commands its hot loops (the devices' emulator has a pipe protocol of its
#: own, with other names).
CALLERS = ("api", "cli", "hotloop")
SPEC = SessionSpec(1, "phantom:workpiece", 0.5, None)


@pytest.fixture
def ctx():
    dispatcher = Dispatcher()
    dispatcher.add(build_session(SPEC))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        yield CommandContext(dispatcher, threading.Lock(), threading.Event(), sock)


def test_every_command_the_server_sends_has_a_handler():
    sent: set[str] = set()
    for path in (p for room in CALLERS for p in (SERVER / room).rglob("*.py")):
        sent |= set(re.findall(r'\bcall\(\s*"(\w+)"', path.read_text(encoding="utf-8")))
    assert {"stats", "stop", "add_session", "set_engine"} <= sent  # the scan finds the calls
    assert sent <= set(COMMANDS), sent - set(COMMANDS)


def test_the_table_answers_on_the_pipe_until_stop(ctx):
    ours, theirs = Pipe()
    server = threading.Thread(target=serve_commands, args=(theirs, ctx), daemon=True)
    server.start()
    ours.send(("configure", {"session_id": 1, "config": SessionConfig(gap_s=0.1)}))
    assert ours.recv() == ("ok", None)
    assert ctx.dispatcher.sessions[1].config.gap_s == 0.1
    ours.send(("no_such_command", {}))
    assert ours.recv() == ("error", ("invalid", "unknown command 'no_such_command'"))
    ours.send(("session_state", {"session_id": 7}))
    assert ours.recv() == ("error", ("not_found", "no session 7"))
    ours.send(("stats", {}))
    status, stats = ours.recv()
    assert status == "ok" and 1 in stats["sessions"]
    ours.send(("stop", {}))
    assert ours.recv() == ("ok", None)
    server.join(5.0)
    assert not server.is_alive() and ctx.stopping.is_set()


def test_the_parent_going_away_stops_the_loop(ctx):
    ours, theirs = Pipe()
    server = threading.Thread(target=serve_commands, args=(theirs, ctx), daemon=True)
    server.start()
    ours.close()
    server.join(5.0)
    assert not server.is_alive() and ctx.stopping.is_set()


def test_a_replaced_session_goes_on_from_the_old_ones_stream_numbers(ctx):
    old = ctx.dispatcher.sessions[1]
    old.hello()
    with pytest.raises(SessionExists):
        run_command(ctx, "add_session", {"spec": SPEC})
    info = run_command(ctx, "replace_session", {"spec": SPEC})
    new = ctx.dispatcher.sessions[1]
    assert new is not old and new.next_stream == old.next_stream
    assert info == {"voxel_mm": 0.5}


def test_removing_answers_whether_there_was_a_session(ctx):
    assert run_command(ctx, "recording_status", {"session_id": 1}) is None  # not recording
    assert run_command(ctx, "remove_session", {"session_id": 1}) is True
    assert run_command(ctx, "remove_session", {"session_id": 1}) is False
    with pytest.raises(KeyError):
        run_command(ctx, "restart_stream", {"session_id": 1})


def test_sessions_being_restored_are_held_until_added_or_the_restore_ends(ctx):
    """After a restart the new loop is told which sessions come back (``restoring``): their
    datagrams go unanswered (never UNKNOWN_SESSION) until each is added, or until
    ``restored`` ends the wait for one that did not come back."""
    from burrforce.proto.codec import decode_server_message, encode_pose
    from burrforce.proto.messages import UNKNOWN_SESSION, WRONG_STREAM, Pose

    d = ctx.dispatcher
    d.restoring.update({2, 3})

    def pose(sid: int) -> bytes:
        return encode_pose(Pose(sid, 9, 9000, (5.0, 0.0, 30.0), (0.0, 0.0, 0.0, 1.0), 0.0,
                                False, stream=1234))

    assert d.handle(pose(2), 1) is None and d.handle(pose(3), 2) is None
    assert decode_server_message(d.handle(pose(4), 3)).error == UNKNOWN_SESSION
    assert (d.counters["restoring"], d.counters["unknown_session"]) == (2, 1)
    run_command(ctx, "add_session", {"spec": SessionSpec(2, "phantom:workpiece", 0.5, None)})
    assert decode_server_message(d.handle(pose(2), 4)).error == WRONG_STREAM  # back
    assert d.handle(pose(3), 5) is None
    run_command(ctx, "restored", {})
    assert decode_server_message(d.handle(pose(3), 6)).error == UNKNOWN_SESSION
    assert d.restoring == set()
