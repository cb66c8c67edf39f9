"""burrforce client: talks to a running burrforce server over its UDP wire protocol."""

from .aio import AsyncBurrClient
from .trajectory import StreamResult, Waypoint, line, stream
from .udp import BurrClient, Result, ServerError

__all__ = ["AsyncBurrClient", "BurrClient", "Result", "ServerError", "StreamResult",
           "Waypoint", "line", "stream"]
