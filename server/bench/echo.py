"""A bare UDP echo: the floor the latency benchmark compares the protocol against.

``python -m burrforce.server.bench.echo`` binds 127.0.0.1 on a free port, prints it, and
sends every datagram back until it receives ``b"stop"``. Same interpreter, same blocking
socket calls as the hot loop; nothing else.
"""

from __future__ import annotations

import socket
import sys


def main() -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    print(sock.getsockname()[1], flush=True)
    recv = sock.recvfrom
    send = sock.sendto
    while True:
        data, addr = recv(2048)
        if data == b"stop":
            return
        send(data, addr)


if __name__ == "__main__":
    sys.exit(main())
