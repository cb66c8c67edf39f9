"""Start an emulator process from tests and benches, and talk to it.

    with EmulatedUsb("falcon", firmware_loaded=True) as emu:
        subprocess.run([sys.executable, "driver_script.py"], env=emu.client_env(), check=True)
        emu.control("set_hand", target_mm=[0, 0, 10])
        print(emu.state()["cycles"])

The driver must run in a process *started* with :meth:`EmulatedUsb.client_env` (LD_PRELOAD
cannot be added to a running process). Stop that process before closing the emulator: a
client whose emulator is gone is aborted by libumockdev-preload on its next ioctl.
"""

from __future__ import annotations

import json
import os
import selectors
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from .control import ControlClient, EmulatorCommandError
from .serve import KINDS
from .usbfs import EmulationUnavailable, preload_library, require_umockdev

__all__ = [
    "EmulatedUsb",
    "EmulationUnavailable",
    "EmulatorCommandError",
    "emulation_unavailable_reason",
]


#: The folder that holds the ``support`` package (tests/): the emulator process imports it from
#: there, as the tests do (it is not part of the installed burrforce).
SUPPORT_ROOT = Path(__file__).resolve().parents[2]


def emulation_unavailable_reason() -> str | None:
    """None when umockdev emulation can run here; else why not (for ``pytest.skip``)."""
    try:
        require_umockdev()
        preload_library()
    except EmulationUnavailable as exc:
        return str(exc)
    return None


class EmulatedUsb:
    """An emulator process serving one emulated USB device.

    Args:
        kind: ``falcon``, ``board`` or ``loopback`` (``serve.KINDS``).
        bus, devnum: the device's USB address.
        reap_hold_ms: see ``usbfs.UsbfsEmulator`` (``reap_hold_s``).
        startup_timeout_s: how long to wait for the emulator's ready line.
        python: the interpreter to run it with (default: this one).
        **options: the device's options (its class's constructor keywords).
    """

    def __init__(self, kind: str, *, bus: int = 1, devnum: int = 2, reap_hold_ms: float = 0.5,
                 startup_timeout_s: float = 30.0, python: str | None = None,
                 **options: Any) -> None:
        if kind not in KINDS:
            raise ValueError(f"unknown emulated device {kind!r}; one of: {', '.join(KINDS)}")
        self.kind = kind
        self.options = options
        self.argv = [python or sys.executable, "-m", "support.emulation", kind,
                     "--options", json.dumps(options), "--bus", str(bus), "--devnum",
                     str(devnum), "--reap-hold-ms", str(reap_hold_ms), "--exit-on-stdin-eof"]
        self.startup_timeout_s = startup_timeout_s
        self.info: dict[str, Any] = {}
        self._proc: subprocess.Popen[bytes] | None = None
        self._client: ControlClient | None = None

    def start(self) -> EmulatedUsb:
        """Start the emulator and wait until it serves. EmulationUnavailable when umockdev
        is missing; RuntimeError with the emulator's message when it fails to start."""
        reason = emulation_unavailable_reason()
        if reason:
            raise EmulationUnavailable(reason)
        if self.kind == "falcon":
            # Compiled here first, into the cache the emulator process shares (NUMBA_CACHE_DIR
            # is inherited): it then loads the mechanism's kernels instead of compiling them
            # within its start-up timeout. (`burrforce compile` no longer does: the emulator
            # is not part of the installed package.)
            from .mechanism import warm_up

            warm_up()
        env = dict(os.environ)
        path = env.get("PYTHONPATH")
        env["PYTHONPATH"] = f"{SUPPORT_ROOT}{os.pathsep}{path}" if path else str(SUPPORT_ROOT)
        self._proc = subprocess.Popen(self.argv, stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, env=env)
        line = self._read_ready_line()
        try:
            info = json.loads(line)
        except json.JSONDecodeError:
            self.close()
            raise RuntimeError(f"emulator printed {line!r} instead of its ready line") from None
        if not info.get("ready"):
            self.close()
            raise RuntimeError(f"emulator {self.kind} failed to start: {info.get('error')}")
        self.info = info
        self._client = ControlClient(info["control"])
        return self

    def _read_ready_line(self) -> str:
        assert self._proc is not None and self._proc.stdout is not None
        deadline = time.monotonic() + self.startup_timeout_s
        with selectors.DefaultSelector() as sel:
            sel.register(self._proc.stdout, selectors.EVENT_READ)
            buf = b""
            while b"\n" not in buf:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not sel.select(remaining):
                    self.close()
                    raise RuntimeError(f"emulator {self.kind} did not start within "
                                       f"{self.startup_timeout_s} s")
                chunk = os.read(self._proc.stdout.fileno(), 65536)
                if not chunk:
                    code = self._proc.wait()
                    raise RuntimeError(f"emulator {self.kind} exited ({code}) before it was "
                                       f"ready: {buf.decode(errors='replace')}")
                buf += chunk
        return buf.split(b"\n", 1)[0].decode()

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc else None

    def client_env(self, base: dict[str, str] | None = None) -> dict[str, str]:
        """The environment to start a driver process with: ``base`` (default os.environ)
        plus LD_PRELOAD (prepended) and UMOCKDEV_DIR."""
        if not self.info:
            raise RuntimeError("start the emulator first")
        env = dict(os.environ if base is None else base)
        ours = self.info["env"]
        old = env.get("LD_PRELOAD")
        env["LD_PRELOAD"] = f"{ours['LD_PRELOAD']}:{old}" if old else ours["LD_PRELOAD"]
        env["UMOCKDEV_DIR"] = ours["UMOCKDEV_DIR"]
        return env

    def control(self, cmd: str, **args: Any) -> Any:
        """Run a control command (``commands`` lists them); EmulatorCommandError on refusal."""
        if self._client is None:
            raise RuntimeError("start the emulator first")
        return self._client.call(cmd, **args)

    def state(self) -> dict[str, Any]:
        return self.control("state")

    def unplug(self) -> None:
        """Pull the emulated plug (pending transfers fail, later ones get ENODEV)."""
        self.control("unplug")

    def replug(self) -> None:
        """Plug it back in, freshly powered; the host must open it again (old handles stay
        dead; a libusb context that listed the device before can open it again)."""
        self.control("replug")

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the emulator (asks politely, then terminates, then kills)."""
        if self._client is not None:
            try:
                self._client.call("shutdown")
            except (OSError, ConnectionError, EmulatorCommandError):
                pass
            self._client.close()
            self._client = None
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if proc.stdin:
            proc.stdin.close()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if proc.stdout:
            proc.stdout.close()

    def __enter__(self) -> EmulatedUsb:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
