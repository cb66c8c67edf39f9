"""Entry point of the hot-loop process: ``python -m burrforce.server.hotloop.child FD``.

FD is one end of a socket pair the parent (``HotLoopProcess``) holds the other end of.
"""

from __future__ import annotations

import sys
from multiprocessing.connection import Connection

from .process import child_main

if __name__ == "__main__":
    child_main(Connection(int(sys.argv[1])))
