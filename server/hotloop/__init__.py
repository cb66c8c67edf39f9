"""The UDP hot loop: sessions, the protocol in front of them, and the process that runs them.

Rooms, lower first: ``errors`` (how a command fails, as data), ``bucket``, ``wire`` and
``stages`` (the per-packet kernels), ``telemetry`` (a session's state in a mapped file),
``session_config`` and ``session`` (one engine's burr on one bone), ``dispatch`` (decode → tag
→ order → tick → encode), ``wake`` and ``loop`` (the socket loop), ``spec`` (what a worker
runs), ``commands`` (the command table), ``child`` (the loop process's main), ``handle``
(``HotLoopProcess``, the parent's side) and ``pool`` (many workers).
"""

from importlib import import_module

#: What the package exports, and the room each comes from: imported on first use (PEP 562),
#: so a module that needs only a light room (``wake``, ``spec``'s names) does not import the
#: whole loop, numba and the bone with it (``burrforce serve`` spawns its loops sooner).
_EXPORTS = {"Dispatcher": "dispatch", "HotLoopProcess": "handle", "Session": "session",
            "SessionConfig": "session_config", "DEFAULT_BONE": "spec",
            "HotLoopConfig": "loop_config", "SessionSpec": "spec", "build_session": "spec"}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_EXPORTS})
