"""A failed hot-loop command crosses the pipe as (kind, message) data: a real loop process,
each kind of failure, and nothing that parses an exception's text."""

from __future__ import annotations

import errno

import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.bone.loaders import BoneFileError
from burrforce.server.hotloop import HotLoopConfig, HotLoopProcess, SessionConfig, SessionSpec
from burrforce.server.hotloop.errors import KINDS, CommandError, SessionExists, classify


@pytest.fixture(scope="module")
def hot():
    config = HotLoopConfig(sessions=(SessionSpec(1, "phantom:workpiece", 0.5, None),))
    with HotLoopProcess(config) as hot:
        yield hot


def _failure(hot: HotLoopProcess, command: str, **kwargs: object) -> CommandError:
    with pytest.raises(CommandError) as err:
        hot.call(command, **kwargs)
    return err.value


def test_a_missing_session_is_not_found_with_its_id(hot):
    err = _failure(hot, "configure", session_id=99, config=SessionConfig())
    assert err.kind == "not_found" and err.message == "no session 99"


def test_a_session_id_in_use_is_a_conflict(hot):
    err = _failure(hot, "add_session", spec=SessionSpec(1, "phantom:workpiece", 0.5, None))
    assert err.kind == "conflict" and err.message == "session 1 exists"


def test_a_bad_bone_and_bad_arguments_are_invalid(hot):
    err = _failure(hot, "add_session", spec=SessionSpec(2, "phantom:nonesuch", 0.5, None))
    assert err.kind == "invalid" and "nonesuch" in err.message
    assert "Error:" not in err.message  # the message, not a traceback's line
    err = _failure(hot, "configure", session_id=1, config="not a config")
    assert err.kind == "invalid" and "SessionConfig" in err.message
    err = _failure(hot, "no_such_command")
    assert err.kind == "invalid" and "no_such_command" in err.message


def test_the_loop_answers_again_after_each_failure(hot):
    assert hot.call("configure", session_id=1, config=SessionConfig()) is None


def test_a_stopped_loop_is_unavailable():
    config = HotLoopConfig(sessions=(SessionSpec(1, "phantom:workpiece", 0.5, None),))
    hot = HotLoopProcess(config)
    hot.start()
    hot.stop()
    err = _failure(hot, "stats")
    assert err.kind == "unavailable" and "not running" in err.message


@pytest.mark.parametrize(("exc", "kind"), [
    (KeyError("no session 3"), "not_found"),
    (SessionExists("session 3 exists"), "conflict"),
    (BoneFileError("ct.nrrd", "truncated"), "invalid"),
    (TypeError("spec must be a SessionSpec"), "invalid"),
    (ValueError("radius"), "invalid"),
    (ZeroDivisionError("division by zero"), "internal"),
    (OSError(errno.ENOSPC, "No space left on device", "meta.json"), "no_room"),
])
def test_each_exception_has_its_kind(exc, kind):
    err = classify(exc)
    assert err.kind == kind
    if kind == "internal":  # a bug: the type is named so it can be found
        assert err.message == "ZeroDivisionError: division by zero"
    elif kind == "not_found":  # a KeyError's text unquoted
        assert err.message == exc.args[0]
    elif kind == "no_room":  # said as a full disk, with the file
        assert err.message == f"the disk is full: {exc}" and "meta.json" in err.message
    else:
        assert err.message == str(exc)


@given(st.sampled_from(KINDS), st.text())
def test_the_data_round_trips(kind, message):
    err = CommandError.from_data(CommandError(kind, message).as_data())
    assert (err.kind, err.message) == (kind, message)


@given(st.one_of(st.text(), st.tuples(st.text(), st.text()), st.none(), st.integers()))
def test_anything_else_a_child_sends_is_an_internal_error_keeping_its_text(data):
    err = CommandError.from_data(data)
    if not (isinstance(data, tuple) and data[0] in KINDS):
        assert err.kind == "internal" and err.message == str(data)


def test_an_unknown_kind_is_refused():
    with pytest.raises(ValueError, match="kind"):
        CommandError("teapot", "no")
