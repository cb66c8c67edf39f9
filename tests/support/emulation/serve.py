"""The emulator process: build one emulated device, serve it, print how to reach it.

``python -m support.emulation KIND [--options JSON] ...`` prints **one**
JSON line on stdout, then serves until SIGTERM/SIGINT, the ``shutdown`` command, or (with
``--exit-on-stdin-eof``) its stdin closing::

    {"ready": true, "kind": "falcon", "pid": 1234,
     "env": {"LD_PRELOAD": ".../libumockdev-preload.so.0", "UMOCKDEV_DIR": "/tmp/umockdev.X"},
     "control": "/tmp/burrforce-emu-Y/control.sock",
     "device": {"vendor_id": 1027, "product_id": 52040, "bus": 1, "devnum": 2,
                "node": "/dev/bus/usb/001/002"}}

or, when it cannot start, ``{"ready": false, "error": "..."}`` and exit status 2.
Run the driver under ``env`` (the whole process must start with it); script the device over
the control socket (``control.py``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
from typing import Any

#: Emulated device kinds: name → "module:class" (imported on use: numba/numpy stay unloaded
#: until a kind needs them).
KINDS = {
    "falcon": "support.emulation.falcon:EmulatedFalcon",
    "board": "support.emulation.board:EmulatedBoard",
    "loopback": "support.emulation.loopback:LoopbackFunction",
}


def make_function(kind: str, options: dict[str, Any]) -> Any:
    """An emulated device of ``kind`` built with ``options`` (its constructor's keywords)."""
    if kind not in KINDS:
        raise ValueError(f"unknown emulated device {kind!r}; one of: {', '.join(KINDS)}")
    module, _, name = KINDS[kind].partition(":")
    cls = getattr(importlib.import_module(module), name)
    try:
        return cls(**options)
    except TypeError as exc:
        raise ValueError(f"bad options for {kind}: {exc}") from None


def _parse(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m support.emulation",
        description="Emulate a USB device (umockdev + usbfs) for drivers under test.")
    parser.add_argument("kind", choices=sorted(KINDS))
    parser.add_argument("--options", default="{}",
                        help="JSON object of the device's options, e.g. "
                             "'{\"firmware_loaded\": true}'")
    parser.add_argument("--firmware-loaded", action="store_true",
                        help="falcon: start with the firmware already loaded")
    parser.add_argument("--homed", action="store_true", help="falcon: start homed")
    parser.add_argument("--bus", type=int, default=1)
    parser.add_argument("--devnum", type=int, default=2)
    parser.add_argument("--reap-hold-ms", type=float, default=0.5,
                        help="longest hold of an empty-handed REAPURBNDELAY (ms)")
    parser.add_argument("--exit-on-stdin-eof", action="store_true",
                        help="exit when stdin closes (the launcher's parent went away)")
    return parser.parse_args(argv)


def _print_line(payload: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(payload) + "\n")
    sys.stdout.flush()


def main(argv: list[str] | None = None) -> int:
    args = _parse(argv)
    from .usbfs import UsbfsEmulator  # keeps `--help` free of gi

    try:
        options = json.loads(args.options)
        if not isinstance(options, dict):
            raise ValueError("--options must be a JSON object")
        if args.firmware_loaded:
            options["firmware_loaded"] = True
        if args.homed:
            options["homed"] = True
        function = make_function(args.kind, options)
        emulator = UsbfsEmulator(function, bus=args.bus, devnum=args.devnum,
                                 reap_hold_s=args.reap_hold_ms * 1e-3).start()
    except Exception as exc:  # reported to the launcher, not a traceback
        _print_line({"ready": False, "error": f"{type(exc).__name__}: {exc}"})
        return 2

    stop = threading.Event()
    from .control import ControlServer

    def handle(cmd: str, cmd_args: dict[str, Any]) -> Any:
        if cmd == "ping":
            return "pong"
        if cmd == "stats":
            return emulator.stats()
        if cmd == "unplug":
            emulator.unplug()
            return True
        if cmd == "replug":
            emulator.replug()
            return True
        if cmd == "shutdown":
            stop.set()
            return True
        commands = function.commands()
        if cmd == "commands":
            return sorted([*commands, "ping", "stats", "unplug", "replug", "shutdown", "commands"])
        if cmd not in commands:
            raise ValueError(f"unknown command {cmd!r}; try 'commands'")
        with emulator.lock:
            result = commands[cmd](**cmd_args)
        emulator.wake()
        return result

    control_dir = tempfile.mkdtemp(prefix="burrforce-emu-")
    server = ControlServer(os.path.join(control_dir, "control.sock"), handle).start()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.exit_on_stdin_eof:
        def watch_stdin() -> None:
            # os.read, not sys.stdin: a daemon thread blocked in a buffered read can abort
            # the interpreter at shutdown (_enter_buffered_busy).
            while os.read(sys.stdin.fileno(), 4096):
                pass
            stop.set()
        threading.Thread(target=watch_stdin, daemon=True).start()

    f = function
    _print_line({"ready": True, "kind": args.kind, "pid": os.getpid(),
                 "env": emulator.client_env(), "control": server.path,
                 "device": {"vendor_id": f.vendor_id, "product_id": f.product_id,
                            "bus": emulator.bus, "devnum": emulator.devnum,
                            "node": emulator.node, "syspath": emulator.syspath}})
    try:
        while not stop.wait(0.5):
            pass
    finally:
        server.close()
        emulator.stop()
        shutil.rmtree(control_dir, ignore_errors=True)
    return 0
