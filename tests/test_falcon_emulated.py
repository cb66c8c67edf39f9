"""FalconDevice, unchanged, through real pyusb + libusb against the umockdev-emulated Falcon
(``support.emulation``): firmware upload, homing, force rendering, clamping, velocity,
zeroing on close, unplugging.

The driver runs in a child process started under the emulator's preload (LD_PRELOAD cannot
be added to a running process) and obeys one JSON command per stdin line, answering one
JSON line each. Skips, with the reason, where umockdev/PyGObject are missing.
"""

from __future__ import annotations

import hashlib
import json
import os
import selectors
import subprocess
import sys
import time

import numpy as np
import pytest

from burrforce.server.devices.falcon import protocol as P
from burrforce.server.devices.falcon.kinematics import commands_to_torques, end_effector_force
from burrforce.server.haptics.profiles import PROFILES
from support.emulation import EmulatedUsb, emulation_unavailable_reason

pytestmark = pytest.mark.skipif(emulation_unavailable_reason() is not None,
                                reason=f"USB emulation unavailable: "
                                       f"{emulation_unavailable_reason()}")

DRIVER = r"""
import json, sys, time
import numpy as np
from burrforce.server.devices.base import DeviceError
from burrforce.server.devices.falcon import FalconDevice

def emit(**kv):
    print(json.dumps(kv), flush=True)

def state_dict(s):
    return {"position_mm": s.position_mm.tolist(), "velocity_mm_s": s.velocity_mm_s.tolist(),
            "buttons": s.buttons, "t_ns": s.t_ns}

dev = FalconDevice(firmware=json.loads(sys.argv[1]))
try:
    dev.open()
except DeviceError as exc:
    emit(error=type(exc).__name__, message=str(exc), is_open=dev.is_open)
    raise SystemExit(0)
emit(opened=True, firmware_status=dev.firmware_status, serial=dev.info.serial)
for line in sys.stdin:
    cmd = json.loads(line)
    op = cmd["op"]
    try:
        if op == "home":
            messages = []
            homed = dev.home(timeout_s=cmd["home_s"], progress=messages.append)
            emit(homed=homed, messages=messages, cycles=dev.cycles)
        elif op == "cycles":
            force = np.array(cmd["force"], dtype=float)
            t0 = time.perf_counter()
            for _ in range(cmd["n"]):
                s = dev.cycle(force)
            emit(s_per_cycle=(time.perf_counter() - t0) / cmd["n"], homed=dev.homed,
                 fk_failures=dev.fk_failures, bad_packets=dev.bad_packets, **state_dict(s))
        elif op == "trace":
            # n cycles at zero force: each one's time, velocity and whether it stalled. With
            # stall_every, every stall_every-th cycle reads its reply stall_ms late, as when
            # the host is preempted while the reply is in flight.
            link = dev._link
            stalled = [False]
            def late_read(timeout_ms, read=link.read_payload):
                if not stalled[0]:
                    stalled[0] = True
                    time.sleep(cmd["stall_ms"] / 1000.0)
                return read(timeout_ms)
            rows = []
            for k in range(cmd["n"]):
                if cmd.get("stall_every") and k % cmd["stall_every"] == 0 and k > 0:
                    link.read_payload = late_read
                s = dev.cycle(np.zeros(3))
                if "read_payload" in vars(link):
                    del link.read_payload
                rows.append([s.t_ns, int(stalled[0]), *s.velocity_mm_s.tolist()])
                stalled[0] = False
            emit(rows=rows)
        elif op == "cycle_until_error":
            n = 0
            while True:
                dev.cycle(np.zeros(3))
                n += 1
        elif op == "close":
            dev.close()
            dev.close()
            emit(closed=True, is_open=dev.is_open)
            break
    except DeviceError as exc:
        emit(error=type(exc).__name__, message=str(exc), t_ns=time.monotonic_ns())
"""


class Driver:
    """The driver process: send it commands, read its answers (with a timeout)."""

    def __init__(self, emu: EmulatedUsb, firmware: str | None) -> None:
        self.proc = subprocess.Popen([sys.executable, "-c", DRIVER, json.dumps(firmware)],
                                     env=emu.client_env(), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self.proc.stdout, selectors.EVENT_READ)
        self._buf = b""

    def answer(self, timeout_s: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0 or not self._sel.select(left):
                raise AssertionError(f"the driver did not answer within {timeout_s} s")
            chunk = os.read(self.proc.stdout.fileno(), 65536)
            if not chunk:
                err = self.proc.stderr.read().decode(errors="replace")
                raise AssertionError(f"the driver exited ({self.proc.wait()}):\n{err[-4000:]}")
            self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        return json.loads(line)

    def __call__(self, op: str, timeout_s: float = 60.0, **args) -> dict:
        self.proc.stdin.write((json.dumps({"op": op, **args}) + "\n").encode())
        self.proc.stdin.flush()
        return self.answer(timeout_s)

    def finish(self) -> None:
        try:
            if self.proc.stdin and not self.proc.stdin.closed:
                self.proc.stdin.close()
            self.proc.wait(30)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait()
            self._sel.close()
            self.proc.stdout.close()
            self.proc.stderr.close()


def sweep_path(amplitude_mm: float = 25.0, period_s: float = 1.0, seconds: float = 60.0):
    """A hand path sweeping the grip along z (every axis turns), for homing."""
    return [[k * period_s / 2, 0.0, 0.0, amplitude_mm * (-1) ** k]
            for k in range(int(2 * seconds / period_s) + 1)]


def force_at(emu: EmulatedUsb) -> np.ndarray:
    """The force the emulated motors exert now (N): their last command at the grip's position."""
    state = emu.state()
    tau = commands_to_torques(np.array(state["motor_command"], dtype=float))
    return end_effector_force(np.array(state["position_m"]), tau)


def test_driver_uploads_firmware_homes_renders_and_zeroes(tmp_path, record_property):
    image = bytes((i * 7 + 3) & 0xFF for i in range(3000))  # a dummy: the emulator runs none
    firmware = tmp_path / "falcon_firmware.bin"
    firmware.write_bytes(image)
    with EmulatedUsb("falcon", homing_travel_counts=400) as emu:
        assert emu.state()["mode"] == "bootloader"
        drv = Driver(emu, str(firmware))
        try:
            opened = drv.answer()
            assert opened.get("opened"), opened
            state = emu.state()
            assert state["mode"] == "firmware" and state["uploads"] == 1
            assert state["upload_bytes"] == len(image)
            assert state["upload_sha256"] == hashlib.sha256(image).hexdigest()
            assert "loaded firmware" in opened["firmware_status"]
            assert hashlib.sha256(image).hexdigest()[:16] in opened["firmware_status"]
            assert opened["serial"].startswith("usb:")

            # Before homing: zero force, red light, homing bit set.
            before = drv("cycles", n=20, force=[0.0, 0.0, 5.0])
            assert not before["homed"]
            state = emu.state()
            assert state["motor_command"] == [0, 0, 0] and state["homing_mode"]
            assert state["leds"] == P.LED_RED

            # The user sweeps the grip through its range.
            emu.control("set_hand", path=sweep_path())
            homing = drv("home", home_s=30.0)
            assert homing["homed"], homing
            assert any("pull the grip" in m.lower() for m in homing["messages"])
            assert emu.state()["leds"] == P.LED_GREEN

            # Hold the grip still (a stiff, well damped hand) and read its position.
            emu.control("set_hand", target_mm=[5.0, -3.0, 8.0], stiffness_N_mm=1.0,
                        damping_N_s_mm=0.03)
            held = drv("cycles", n=600, force=[0.0, 0.0, 0.0])
            true_mm = np.array(emu.state()["position_mm"])
            assert np.abs(np.array(held["position_mm"]) - true_mm).max() < 0.2
            assert np.abs(held["velocity_mm_s"]).max() < 5.0
            assert held["fk_failures"] == 0 and held["bad_packets"] == 0

            # A force is rendered as commanded (the emulator pushes with the real kinematics).
            pushed = drv("cycles", n=600, force=[1.0, -0.5, 2.0])
            np.testing.assert_allclose(force_at(emu), [1.0, -0.5, 2.0], atol=0.03)
            assert np.abs(np.array(pushed["position_mm"]) - emu.state()["position_mm"]).max() \
                < 0.2

            # Too strong: clamped to the profile's max force, direction kept.
            drv("cycles", n=50, force=[0.0, 0.0, 80.0])
            f = force_at(emu)
            assert np.linalg.norm(f) == pytest.approx(PROFILES["falcon"].max_force_N, rel=0.02)
            assert f[2] > 0.99 * np.linalg.norm(f)
            # Not a number: zero force.
            drv("cycles", n=5, force=[float("nan"), 0.0, 1.0])
            assert emu.state()["motor_command"] == [0, 0, 0]

            # Velocity: the hand drags the grip at 6 mm/s along x for 6 s (slow and long, so
            # a loaded machine still measures on the ramp).
            emu.control("place", position_mm=[-18.0, 0.0, 0.0])
            emu.control("set_hand", path=[[0.0, -18.0, 0.0, 0.0], [6.0, 18.0, 0.0, 0.0]])
            drv("cycles", n=100, force=[0.0, 0.0, 0.0])   # the grip settles onto the ramp
            ramp = np.array(drv("trace", n=400)["rows"])
            true_v = np.array(emu.state()["velocity_m_s"]) * 1e3
            assert true_v[0] == pytest.approx(6.0, abs=1.5)   # still on the ramp
            check_ramp_velocity(ramp, true_v)
            ms_per_cycle = float(np.median(np.diff(ramp[:, 0]))) * 1e-6
            record_property("falcon_driver_ms_per_cycle_emulated", round(ms_per_cycle, 3))
            print(f"\nFalconDevice.cycle through the emulation: {ms_per_cycle:.2f} ms")

            drv("cycles", n=50, force=[0.0, 0.0, 3.0])
            assert emu.state()["motor_command"] != [0, 0, 0]
            closed = drv("close")
            assert closed == {"closed": True, "is_open": False}
            state = emu.state()
            assert state["motor_command"] == [0, 0, 0] and state["leds"] == 0
        finally:
            drv.finish()


def check_ramp_velocity(rows: np.ndarray, true_v: np.ndarray) -> np.ndarray:
    """The estimates of a ``trace`` on the steady ramp against the grip's true velocity
    (mm/s): their median within 1 mm/s, and at most 2 % of them off by more than 2.5 mm/s
    (a loaded machine may stall the emulator itself between a command and its reading).
    Returns each sample's worst-axis error (mm/s)."""
    v = rows[:, 2:5]
    np.testing.assert_allclose(np.median(v, axis=0), true_v, atol=1.0)
    err = np.abs(v - true_v).max(axis=1)
    assert np.mean(err > 2.5) <= 0.02, (np.sort(err)[-10:], np.nonzero(err > 2.5)[0])
    return err


def test_a_host_stall_while_the_reply_is_in_flight_does_not_jolt_the_velocity():
    """The firmware reads its encoders when a command arrives. If the host is preempted
    before it reads the reply, that reading must still be timed by when it was taken, or
    the velocity estimate jumps (tens of mm/s) at a steady 6 mm/s."""
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True,
                     start_mm=[-18.0, 0.0, 0.0]) as emu:
        drv = Driver(emu, None)
        try:
            drv.answer()
            assert drv("home", home_s=5.0)["homed"]
            emu.control("set_hand", stiffness_N_mm=1.0, damping_N_s_mm=0.03,
                        path=[[0.0, -18.0, 0.0, 0.0], [6.0, 18.0, 0.0, 0.0]])
            drv("cycles", n=100, force=[0.0, 0.0, 0.0])
            rows = np.array(drv("trace", n=400, stall_every=20, stall_ms=15.0)["rows"])
            true_v = np.array(emu.state()["velocity_m_s"]) * 1e3
            assert true_v[0] == pytest.approx(6.0, abs=1.5)
            stalled = np.nonzero(rows[:, 1])[0]
            assert len(stalled) == 19
            # The stall did delay the stream (on whichever side of the stalled cycle's stamp).
            assert np.all((rows[stalled + 1, 0] - rows[stalled - 1, 0]) * 1e-6 > 15.0)
            err = check_ramp_velocity(rows, true_v)
            # The stalled cycle and the two after it: the old stamping put 20-60 mm/s there.
            near = np.concatenate([stalled, stalled + 1, stalled + 2])
            assert np.mean(err[near] > 2.5) <= 0.1, err[near]
        finally:
            drv("close")
            drv.finish()


def test_driver_skips_the_upload_when_firmware_runs():
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True, start_mm=[-4.0, 6.0, 2.0],
                     buttons=0x5) as emu:
        drv = Driver(emu, None)
        try:
            opened = drv.answer()
            assert opened["firmware_status"] == "firmware already running"
            assert emu.state()["uploads"] == 0
            homing = drv("home", home_s=5.0)
            assert homing["homed"] and homing["messages"] == []
            out = drv("cycles", n=200, force=[0.0, 0.0, 0.0])
            assert out["buttons"] == 0x5
            np.testing.assert_allclose(out["position_mm"], emu.state()["position_mm"], atol=0.2)
            drv("close")
        finally:
            drv.finish()


def test_driver_without_firmware_says_where_to_get_it():
    with EmulatedUsb("falcon") as emu:
        drv = Driver(emu, None)
        try:
            failed = drv.answer()
        finally:
            drv.finish()
        assert failed["error"] == "FirmwareError" and not failed["is_open"]
        assert "nvent_firmware.bin" in failed["message"]
        assert emu.state()["mode"] == "bootloader"


def test_unplugging_mid_stream_raises_device_disconnected():
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True) as emu:
        drv = Driver(emu, None)
        try:
            assert drv.answer()["opened"]
            drv("cycles", n=50, force=[0.0, 0.0, 1.0])
            drv.proc.stdin.write(b'{"op": "cycle_until_error"}\n')
            drv.proc.stdin.flush()
            time.sleep(0.2)
            t_unplug = time.monotonic_ns()
            emu.unplug()
            failed = drv.answer(timeout_s=30.0)
            assert failed["error"] == "DeviceDisconnected", failed
            assert (failed["t_ns"] - t_unplug) * 1e-9 < 2.0
            assert drv("close") == {"closed": True, "is_open": False}  # no exception
        finally:
            drv.finish()


#: Opens the Falcon twice with a stop (the device process's StopRequested) landing part-way,
#: once before the device keeps its link and once after, then opens it for real. Counts the
#: link's closes through a wrapper that runs the real close.
STOPPED_OPEN = r"""
import json
import numpy as np
from burrforce.server.devices.falcon import FalconDevice, device as falcon_device
from burrforce.server.devices.falcon.ftdi import FtdiLink
from burrforce.server.devices.loop import StopRequested

closes = []
real_close = FtdiLink.close
def counted_close(link):
    closes.append(link._claimed)
    real_close(link)
FtdiLink.close = counted_close

def stop_once(real):
    state = {"armed": True}
    def stopped(*args, **kwargs):
        if state["armed"]:
            state["armed"] = False
            raise StopRequested
        return real(*args, **kwargs)
    return stopped

for window, name in (("before the link is kept", "replace"), ("after", "_reset_state")):
    owner = falcon_device if name == "replace" else FalconDevice
    real = getattr(owner, name)
    setattr(owner, name, stop_once(real))
    dev = FalconDevice()
    try:
        dev.open()
        outcome = "opened"
    except StopRequested:
        outcome = "stopped"
    setattr(owner, name, real)
    dev.close()
    print(json.dumps({"window": window, "outcome": outcome, "is_open": dev.is_open,
                      "closes": list(closes)}), flush=True)
    closes.clear()
with FalconDevice() as dev:
    state = dev.cycle(np.zeros(3))
print(json.dumps({"reopened": True, "closes": list(closes)}), flush=True)
"""


def test_an_open_stopped_part_way_releases_the_link():
    """A stop landing inside ``open`` (SIGTERM while the device process connects) releases
    the USB link the open had claimed, whether or not the device had kept it yet, and the
    next open finds the Falcon free."""
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True) as emu:
        done = subprocess.run([sys.executable, "-c", STOPPED_OPEN], env=emu.client_env(),
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr[-4000:]
        lines = [json.loads(line) for line in done.stdout.splitlines()]
        for stopped in lines[:2]:
            assert stopped["outcome"] == "stopped" and not stopped["is_open"], stopped
            # Closed once, while it still held the interface.
            assert stopped["closes"] == [True], stopped
        assert lines[2] == {"reopened": True, "closes": [True]}
