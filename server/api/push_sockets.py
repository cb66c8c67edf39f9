"""What every push WebSocket (mesh chunks, telemetry) does alike: the handshake with its
subprotocol, the origin and token checks, the session id, the server-wide count of open
sockets, and noticing that the client left. A close before the handshake would reach the
client as a bare HTTP 403; these close after it, with a code and a reason.

Browsers do not apply the same-origin policy to WebSockets: any page a user visits may open
one to this server, and a token it holds (a page the server itself served, a token pasted
into another tool) would be sent along. A browser always says which page opened the socket
(``Origin``), so one from a foreign origin is refused (4403) unless ``cors_origins`` names it
("*": any). Clients that are not browsers (the engine SDKs, ``burrforce.client.mesh``) send
no ``Origin`` and are not affected."""

from __future__ import annotations

import asyncio
import contextlib
import hmac
from urllib.parse import urlsplit

from fastapi import WebSocket, WebSocketDisconnect


def close_reason(text: str) -> str:
    """A close reason fits in 123 bytes of UTF-8."""
    return text.encode()[:120].decode(errors="ignore")


#: The WebSocket subprotocol a browser offers with its token as ``bearer.TOKEN`` (a browser
#: can set no header, and a token in the URL ends up in access logs).
SUBPROTOCOL = "burrforce"
_BEARER_PROTOCOL = "bearer."
_DEFAULT_PORTS = {"http": 80, "https": 443}


def query_int(text: str | None, name: str, default: int | None, lo: int, hi: int
              ) -> int | None:
    """A WebSocket query's integer ``name`` (``text``; None: ``default``), checked by hand:
    FastAPI would refuse a bad one with a bare HTTP 403 before the handshake. ValueError says
    what is wrong, for the close reason."""
    if text is None:
        return default
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {text!r}") from None
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in {lo}..{hi}, got {value}")
    return value


def _offered(ws: WebSocket) -> list[str]:
    return [p.strip() for p in ws.headers.get("sec-websocket-protocol", "").split(",")
            if p.strip()]


async def accept(ws: WebSocket) -> None:
    """Accept the handshake, choosing ``SUBPROTOCOL`` when the client offered it (a browser
    fails a handshake that does not choose one of the subprotocols it offered)."""
    await ws.accept(subprotocol=SUBPROTOCOL if SUBPROTOCOL in _offered(ws) else None)


def _origin_key(url: str) -> tuple[str, int] | None:
    """(host, port) of an ``Origin`` value, the port defaulted from its scheme."""
    parts = urlsplit(url)
    if parts.scheme not in _DEFAULT_PORTS or not parts.hostname:
        return None
    try:
        return parts.hostname.lower(), parts.port or _DEFAULT_PORTS[parts.scheme]
    except ValueError:  # a port out of range
        return None


def foreign_origin(ws: WebSocket) -> str | None:
    """The ``Origin`` the socket came from if it may not open one: neither this server's own
    (the ``Host`` it was reached at) nor one of ``app.state.ws_origins`` (``cors_origins``;
    "*": any). None without an ``Origin`` (not a browser) or when it may."""
    origin = ws.headers.get("origin")
    if origin is None:
        return None
    allowed = getattr(ws.app.state, "ws_origins", ())
    if "*" in allowed or origin.rstrip("/") in (a.rstrip("/") for a in allowed):
        return None
    own = _origin_key(origin)
    host = ws.headers.get("host", "")
    if own is not None:
        # The Host as the browser reached it: a port left out is the origin scheme's default
        # (also behind a TLS proxy that keeps the Host, where the socket itself is ws://).
        scheme = urlsplit(origin).scheme
        if _origin_key(f"{scheme}://{host}") == own:
            return None
    return origin


async def admitted_session_id(ws: WebSocket, session_id: str, token: str | None) -> int | None:
    """After the query was parsed: the origin (4403) and the token checked (4401) and the
    path's session id parsed (4422), for every push WebSocket; the id, or None once the
    socket is closed."""
    origin = foreign_origin(ws)
    if origin is not None:
        await ws.close(4403, close_reason(f"origin {origin} may not open this WebSocket: add "
                                          "it to the server's cors_origins"))
        return None
    if not _authorized(ws, token):
        await ws.close(4401, "missing or wrong bearer token (Authorization: Bearer TOKEN, "
                             "the subprotocol bearer.TOKEN, or ?token=TOKEN)")
        return None
    # isdecimal on ASCII only: isdigit would take "²", which int() refuses.
    if not (session_id.isascii() and session_id.isdecimal()) or int(session_id) >= 1 << 32:
        await ws.close(4422, close_reason(f"session id must be an integer in 0..2^32-1, got "
                                     f"{session_id!r}"))
        return None
    return int(session_id)


def _authorized(ws: WebSocket, token: str | None) -> bool:
    """The bearer token from the Authorization header, the ``bearer.TOKEN`` subprotocol or
    ``?token=``."""
    expected = ws.app.state.token.encode()
    header = ws.headers.get("authorization", "")
    offered = [p[len(_BEARER_PROTOCOL):] for p in _offered(ws) if p.startswith(_BEARER_PROTOCOL)]
    if header[:7].lower() == "bearer ":
        given = header[7:]
    elif offered:
        given = offered[0]
    else:
        given = token or ""
    return hmac.compare_digest(given.encode(), expected)


async def take_socket_slot(ws: WebSocket, kind: str, limit: int) -> bool:
    """Counts an accepted push WebSocket of ``kind`` against the server's ``limit``; at the
    limit, closes it with 4503 and a reason and answers False. Give the slot back with
    :func:`release_socket_slot`. No lock: one event loop runs every handler."""
    state = ws.app.state
    counts = getattr(state, "push_sockets", None)
    if counts is None:
        counts = state.push_sockets = {}
    open_now = counts.get(kind, 0)
    if open_now >= limit:
        await ws.close(4503, close_reason(f"{open_now} {kind} WebSockets are open, the server's "
                                     f"limit ({limit}): close one"))
        return False
    counts[kind] = open_now + 1
    return True


def release_socket_slot(ws: WebSocket, kind: str) -> None:
    ws.app.state.push_sockets[kind] -= 1


def watch_disconnect(ws: WebSocket) -> tuple[asyncio.Event, asyncio.Task]:
    """An event set when the client of a push-only WebSocket leaves, and the task that
    watches for it (cancel it when done). The client sends nothing; a receive returns only
    when it leaves (or the server shuts down, which uvicorn reports the same way)."""
    gone = asyncio.Event()

    async def watch() -> None:
        with contextlib.suppress(WebSocketDisconnect, RuntimeError):
            while (await ws.receive())["type"] != "websocket.disconnect":
                pass
        gone.set()

    return gone, asyncio.create_task(watch())
