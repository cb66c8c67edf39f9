"""What a 422 adds to pydantic's message so that the sender can fix the request: the closest
valid name for a misspelled field, and the header a body that was not read as JSON lacks."""

from __future__ import annotations

import difflib
from collections.abc import Collection

from starlette.requests import Request
from starlette.routing import Match


def route_of(request: Request) -> object | None:
    """The route that took ``request`` (Starlette keeps it in the scope once matched)."""
    route = request.scope.get("route")
    if route is not None:
        return route
    for candidate in request.app.router.routes:
        if candidate.matches(request.scope)[0] == Match.FULL:
            return candidate
    return None


def body_fields(route: object) -> tuple[str, ...]:
    """The names (and aliases) the body model of ``route`` (a FastAPI ``APIRoute``) takes;
    empty if it has no body model."""
    field = getattr(route, "body_field", None)
    model = getattr(getattr(field, "field_info", None), "annotation", None)
    fields = getattr(model, "model_fields", None)
    if not isinstance(fields, dict):
        return ()
    names = list(fields)
    names += [f.alias for f in fields.values() if getattr(f, "alias", None)]
    return tuple(dict.fromkeys(names))


def closest(name: str, valid: Collection[str]) -> str | None:
    """The valid field ``name`` most likely meant: one that starts with it as a word
    (``Us`` → ``us_n_mm2``), else the closest spelling, ignoring case; None if none is
    close."""
    lower = name.lower()
    by_lower = {v.lower(): v for v in valid}
    prefixed = [v for low, v in by_lower.items() if low.startswith(lower + "_")]
    if prefixed:
        return min(prefixed, key=len)
    match = difflib.get_close_matches(lower, list(by_lower), n=1, cutoff=0.6)
    return by_lower[match[0]] if match else None


#: Errors pydantic gives when the body it got is not the JSON object the route wants.
_NOT_AN_OBJECT = frozenset({"dict_type", "model_attributes_type", "json_invalid",
                            "missing"})


def explained(error: dict, fields: Collection[str], json_body: bool) -> str:
    """pydantic's message for ``error`` with a hint where one helps."""
    msg = str(error.get("msg", ""))
    kind = error.get("type", "")
    loc = list(error.get("loc", ()))
    if kind == "extra_forbidden" and loc:
        guess = closest(str(loc[-1]), fields)
        if guess is not None:
            return f"{msg}: did you mean `{guess}`?"
    if kind in _NOT_AN_OBJECT and loc[:1] == ["body"] and not json_body:
        return (f"{msg} (the body must be a JSON object sent with the header "
                "`Content-Type: application/json`)")
    return msg
