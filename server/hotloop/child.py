"""Entry point of the hot-loop process: ``python -m burrforce.server.hotloop.child FD [BEAT]``.

FD is one end of a socket pair the parent (``HotLoopProcess``) holds the other end of; BEAT,
a datagram socket the loop's heartbeat goes out on.
"""

from __future__ import annotations

import socket
import sys
from multiprocessing.connection import Connection

from .process import child_main

if __name__ == "__main__":
    beat = (socket.socket(fileno=int(sys.argv[2])) if len(sys.argv) > 2 else None)
    child_main(Connection(int(sys.argv[1])), beat)
