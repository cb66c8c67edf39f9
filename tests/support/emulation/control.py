"""The emulator's control channel: JSON lines over a Unix stream socket.

A request is one line ``{"cmd": NAME, "args": {...}}``; the answer is one line
``{"ok": true, "result": ...}`` or ``{"ok": false, "error": "..."}``. Bytes travel as hex
strings. Tests and benches use it to script the emulated device (move the hand, unplug it)
and to read back what it received.
"""

from __future__ import annotations

import json
import os
import socket
import threading
from collections.abc import Callable
from typing import Any

MAX_LINE_BYTES = 1 << 20
#: Answers can be large (motor logs, frame lists): the client reads up to this much.
MAX_ANSWER_BYTES = 256 << 20


class EmulatorCommandError(RuntimeError):
    """The emulator rejected a control command (unknown, bad arguments, or it failed)."""


Handler = Callable[[str, dict[str, Any]], Any]


class ControlServer:
    """Serve ``handler(cmd, args)`` on a Unix socket at ``path``, one thread per client."""

    def __init__(self, path: str, handler: Handler) -> None:
        if len(os.fsencode(path)) >= 108:
            raise ValueError(f"control socket path too long for AF_UNIX (≥ 108 bytes): {path}")
        self.path = path
        self.handler = handler
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.bind(path)
        self._sock.listen(8)
        self._closed = False
        self._thread = threading.Thread(target=self._accept_loop, name="emulator-control",
                                        daemon=True)

    def start(self) -> ControlServer:
        self._thread.start()
        return self

    def close(self) -> None:
        self._closed = True
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass

    def _accept_loop(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, conn.makefile("rb") as reader:
            for line in reader:
                if len(line) > MAX_LINE_BYTES:
                    answer: dict[str, Any] = {"ok": False, "error": "request line too long"}
                else:
                    answer = self._answer(line)
                try:
                    conn.sendall(json.dumps(answer).encode() + b"\n")
                except OSError:
                    return

    def _answer(self, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
            if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
                raise ValueError('a request is {"cmd": NAME, "args": {...}}')
            args = request.get("args") or {}
            if not isinstance(args, dict):
                raise ValueError("args must be an object")
            return {"ok": True, "result": self.handler(request["cmd"], args)}
        except Exception as exc:  # every failure goes back to the caller
            return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}


class ControlClient:
    """Send commands to a :class:`ControlServer`. Not thread-safe: one per thread."""

    def __init__(self, path: str, timeout_s: float = 10.0) -> None:
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self._sock.settimeout(timeout_s)
        self._sock.connect(path)
        self._reader = self._sock.makefile("rb")

    def call(self, cmd: str, **args: Any) -> Any:
        """The command's result; EmulatorCommandError when the emulator rejects it,
        ConnectionError when the emulator is gone."""
        self._sock.sendall(json.dumps({"cmd": cmd, "args": args}).encode() + b"\n")
        line = self._reader.readline(MAX_ANSWER_BYTES)
        if not line:
            raise ConnectionError("the emulator closed its control channel")
        answer = json.loads(line)
        if not answer.get("ok"):
            raise EmulatorCommandError(f"{cmd}: {answer.get('error')}")
        return answer.get("result")

    def close(self) -> None:
        self._reader.close()
        self._sock.close()
