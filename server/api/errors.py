"""Every error the control plane's services raise, and the one place that turns them into HTTP.

The services (sessions, loads, parameters, storage, the worker pool) raise a domain error
saying *what* went wrong, never an HTTP status: :class:`NotFound`, :class:`Conflict`,
:class:`Invalid`, :class:`BadName`, :class:`TooLarge`, :class:`NoRoom`, :class:`Busy`,
:class:`Unavailable`, :class:`Gone`, :class:`Unauthorized`. All derive from :class:`ApiError`,
whose ``detail`` is the message the REST caller reads. :data:`HTTP_STATUS` and
:func:`http_status` are the only mapping to HTTP statuses (the app's exception handler and the
WebSockets' close codes use them).

A hot-loop command fails as ``(kind, message)`` data (``hotloop.errors.CommandError``);
:func:`from_command` turns its kind into a domain error (:data:`COMMAND_ERRORS`). This module
imports nothing else of the API, so every module may import it.
"""

from __future__ import annotations

from ..hotloop.errors import CommandError


class ApiError(Exception):
    """An error the API answers with ``detail`` (its class says which status)."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail

    @property
    def status(self) -> int:
        """The HTTP status this error is answered with (:func:`http_status`)."""
        return http_status(self)


class NotFound(ApiError):
    """What the request names does not exist (a session, a material, a file, a job)."""


class Conflict(ApiError):
    """The request clashes with the present state (an id in use, a session still loading,
    a recording already running, a file in use)."""


class Invalid(ApiError):
    """The request's values do not fit (parameters, a bone, a material, a fit)."""


class BadName(ApiError):
    """A name or path in the request is malformed or leaves its folder."""


class TooLarge(ApiError):
    """An upload exceeds the size limit or the data budget."""


class NoRoom(ApiError):
    """A write (upload, snapshot, export, recording) does not fit in the data budget or on
    the disk (507 Insufficient Storage); the message says what it needed and what is free."""


class Busy(ApiError):
    """The server holds all it may (its maximum of sessions)."""


class Unavailable(ApiError):
    """The hot loop cannot do it now (not running, restarting, not answering, or it failed
    inside), or live data is not there yet: try again."""


class Gone(ApiError):
    """What the work was for went away meanwhile (a session deleted while its bone loaded)."""


class Unauthorized(ApiError):
    """A missing or wrong bearer token."""


#: The HTTP status of each domain error: the one mapping (subclasses map as their base).
HTTP_STATUS: dict[type[ApiError], int] = {
    BadName: 400, Unauthorized: 401, NotFound: 404, Conflict: 409, Gone: 410,
    TooLarge: 413, Invalid: 422, Busy: 429, Unavailable: 503, NoRoom: 507,
}


def from_disk_full(exc: OSError, data_dir: object) -> NoRoom:
    """The answer to a write the disk refused (``whole_files.is_disk_full``) where no route
    said what it was writing: which file, and where to make room."""
    where = f" ({exc.filename})" if exc.filename else ""
    return NoRoom(f"the disk is full: a write{where} was refused ({exc.strerror}). Free "
                  f"space on the disk that holds the data directory ({data_dir}), or delete "
                  "what is stored (GET /v1/storage shows it)")


def http_status(error: ApiError | type[ApiError]) -> int:
    """The HTTP status ``error`` (an instance or a class) is answered with; 500 for an
    ``ApiError`` of no known kind."""
    cls = error if isinstance(error, type) else type(error)
    for base in cls.__mro__:
        if base in HTTP_STATUS:
            return HTTP_STATUS[base]  # type: ignore[index]
    return 500


#: The domain error of each kind of failed hot-loop command (``hotloop.errors.KINDS``).
COMMAND_ERRORS: dict[str, type[ApiError]] = {
    "invalid": Invalid, "not_found": NotFound, "conflict": Conflict, "no_room": NoRoom,
    "unavailable": Unavailable, "internal": Unavailable,
}
#: Kinds whose message reaches the caller as the loop said it; the others are prefixed with
#: what failed.
SAID_AS_IS = frozenset({"invalid", "not_found", "conflict", "no_room"})


def from_command(exc: CommandError) -> ApiError:
    """The domain error a failed hot-loop command is: bad arguments → :class:`Invalid`, a
    missing session → :class:`NotFound`, a session id in use → :class:`Conflict`, a full disk
    → :class:`NoRoom`, a dead loop or anything else → :class:`Unavailable` (its message
    prefixed with what failed)."""
    message = (exc.message if exc.kind in SAID_AS_IS
               else f"the hot loop cannot do it: {exc.message}")
    return COMMAND_ERRORS[exc.kind](message)
