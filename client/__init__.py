"""burrforce client: talks to a running burrforce server over its UDP wire protocol, and to its
REST control plane (``BurrRest``)."""

from .aio import AsyncBurrClient
from .rest import BurrRest, RestError
from .trajectory import StreamResult, Waypoint, line, stream
from .udp import BurrClient, Result, ServerError, ServerGone, StreamTaken

__all__ = ["AsyncBurrClient", "BurrClient", "BurrRest", "RestError", "Result", "ServerError",
           "ServerGone", "StreamResult", "StreamTaken", "Waypoint", "line", "stream"]
