"""How a hot-loop command fails, as data: a kind and a message cross the pipe, never a
traceback's text for the parent to parse.

The child classifies the exception a command raised (:func:`classify`) and answers
``("error", (kind, message))``; the parent's handle raises :class:`CommandError` with the same
kind and message. The control plane maps each kind to its own domain error (and so to an HTTP
status) in one place, ``api.errors``.
"""

from __future__ import annotations

from typing import Literal, get_args

from ..whole_files import is_disk_full

#: What went wrong, from the caller's side:
#:
#: - ``invalid``: the command's arguments do not fit (a bad bone, parameters a burr rejects);
#: - ``not_found``: it names a session the loop does not have;
#: - ``conflict``: it would add what is already there (a session id in use);
#: - ``no_room``: a file it writes did not fit on the disk (ENOSPC, EDQUOT: a recording's);
#: - ``unavailable``: the loop is not running, stopped answering or exited;
#: - ``internal``: anything else (a bug: the message names the exception's type).
Kind = Literal["invalid", "not_found", "conflict", "no_room", "unavailable", "internal"]
KINDS: tuple[str, ...] = get_args(Kind)


class CommandError(RuntimeError):
    """A hot-loop command failed; ``kind`` (one of :data:`KINDS`) says how, ``message`` says
    what, in words fit for the REST caller. A ``RuntimeError``, so callers that only care
    that the loop could not do it keep catching that."""

    def __init__(self, kind: Kind, message: str) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown command error kind {kind!r}")
        super().__init__(message)
        self.kind: Kind = kind
        self.message = message

    def as_data(self) -> tuple[str, str]:
        """``(kind, message)``: what crosses the pipe."""
        return (self.kind, self.message)

    @classmethod
    def from_data(cls, data: object) -> CommandError:
        """The error a child sent (:meth:`as_data`); anything else it could have sent is an
        ``internal`` error with its text, so a malformed answer is never lost."""
        if (isinstance(data, tuple) and len(data) == 2 and data[0] in KINDS
                and isinstance(data[1], str)):
            return cls(data[0], data[1])
        return cls("internal", str(data))


class SessionExists(ValueError):
    """``add_session`` for an id the loop already serves."""


def classify(exc: BaseException) -> CommandError:
    """The :class:`CommandError` a command's exception becomes.

    ``KeyError`` (a session id the loop lacks) is ``not_found`` with the key's text unquoted;
    :class:`SessionExists` is ``conflict``; ``ValueError`` and ``TypeError`` (bad arguments,
    including every bone-file and burr error, which derive from ``ValueError``) are
    ``invalid``; a write the disk had no room for is ``no_room``; a :class:`CommandError`
    keeps its own kind; anything else is ``internal``.
    """
    if isinstance(exc, CommandError):
        return exc
    if isinstance(exc, KeyError):
        text = str(exc.args[0]) if exc.args else "not found"
        return CommandError("not_found", text)
    if isinstance(exc, SessionExists):
        return CommandError("conflict", str(exc))
    if isinstance(exc, (ValueError, TypeError)):
        return CommandError("invalid", str(exc))
    if is_disk_full(exc):
        return CommandError("no_room", f"the disk is full: {exc}")
    return CommandError("internal", f"{type(exc).__name__}: {exc}")
