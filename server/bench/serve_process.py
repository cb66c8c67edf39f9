"""``burrforce serve`` as a user runs it, in a subprocess on free loopback ports: for
benchmarks and end-to-end tests that must measure or exercise the real command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ...client import connection

READY_LINE = "Ctrl-C stops"


@dataclass
class ServeProcess:
    """A running ``burrforce serve``.

    Attributes:
        proc: the process (stdout and stderr merged into ``proc.stdout``, text).
        connection: what it wrote to its connection file.
        connection_file: that file.
        banner: everything it printed until it was ready.
    """

    proc: subprocess.Popen
    connection: connection.Connection
    connection_file: Path
    banner: str

    def stop(self, timeout_s: float = 30.0) -> tuple[int, str]:
        """SIGTERM, then wait; returns the exit code and what it printed after the banner
        (killed if it does not stop in time)."""
        # Read through the same text stream the banner was read from: what its readline()
        # buffered past the banner (a line printed right after it) is there, not in the pipe
        # (communicate(timeout=...) reads the pipe itself and would lose it).
        chunks: list[str] = []
        reader = threading.Thread(target=lambda: chunks.extend(self.proc.stdout),
                                  name="serve-output", daemon=True)
        reader.start()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        # A child still holding the pipe (a hot loop outliving a killed serve) must not hang
        # the caller: what was read by then is returned.
        reader.join(timeout=timeout_s)
        return self.proc.returncode, "".join(chunks)


def spawn_serve(folder: Path, *args: str, timeout_s: float = 300.0,
                env: dict[str, str] | None = None, prefix: tuple[str, ...] = ()) -> ServeProcess:
    """Start ``burrforce serve --udp-port 0 --http-port 0 --data-dir FOLDER/data
    --connection-file FOLDER/connection.json ARGS…`` and wait until it is ready (a cold numba
    cache compiles the kernels first). ``BURRFORCE_TOKEN`` is not passed on; ``env`` is set
    over this process's environment; ``prefix`` runs it under a wrapper command (``prlimit
    … --``).

    Raises:
        RuntimeError: it exited or did not get ready in ``timeout_s``; the message holds what
            it printed.
    """
    conn = folder / "connection.json"
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    env.pop("BURRFORCE_TOKEN", None)
    proc = subprocess.Popen(
        [*prefix, sys.executable, "-m", "burrforce.server.cli", "serve", "--udp-port", "0",
         "--http-port", "0", "--data-dir", str(folder / "data"), "--connection-file",
         str(conn), *args],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    lines = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if READY_LINE in line or not line:
            break
    banner = "".join(lines)
    if READY_LINE not in banner:
        proc.kill()
        proc.wait()
        raise RuntimeError(f"burrforce serve did not start:\n{banner}")
    return ServeProcess(proc, connection.read(conn), conn, banner)
