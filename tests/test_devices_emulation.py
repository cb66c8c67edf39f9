"""USB device emulation (tests/support/emulation): the device models on their own, then real
pyusb + libusb in a preloaded subprocess against emulated devices (umockdev).

The integration tests skip, with the reason, when PyGObject/UMockdev or
libumockdev-preload.so.0 is missing (CI installs umockdev gir1.2-umockdev-1.0)."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.actuators import board_protocol as bp
from burrforce.server.devices.falcon import protocol as fp
from burrforce.server.devices.falcon.kinematics import (
    WORKSPACE_RADIUS_M,
    angle_to_encoder,
    encoder_to_angle,
    forward_kinematics,
    inverse_kinematics,
    motor_torques,
    torques_to_commands,
)
from support.emulation.board import EmulatedBoard
from support.emulation.falcon import EmulatedFalcon
from support.emulation.ftdi import MODEM_STATUS, divisor_to_baud
from support.emulation.function import EmulatedFunction, Endpoint
from support.emulation.launcher import (
    EmulatedUsb,
    EmulatorCommandError,
    emulation_unavailable_reason,
)
from support.emulation.loopback import LoopbackFunction
from support.emulation.mechanism import FalconMechanism


class FakeClock:
    """A monotonic clock (ns) the test advances by hand."""

    def __init__(self, t_ns: int = 1_000_000_000) -> None:
        self.t = t_ns

    def __call__(self) -> int:
        return self.t

    def advance_ms(self, ms: float) -> None:
        self.t += int(ms * 1e6)


def ctrl_out(function: EmulatedFunction, request: int, value: int) -> object:
    return function.control(fp.FTDI_REQUEST_OUT, request, value, fp.FTDI_INDEX, b"")


# -- descriptors and the FTDI model -----------------------------------------------------


def test_descriptors_are_built_from_the_fields():
    f = LoopbackFunction()
    dev = f.device_descriptor()
    (length, kind, bcd_usb, _cls, _sub, _proto, ep0, vid, pid, _bcd, imanu, iprod, iserial,
     nconf) = struct.unpack("<BBHBBBBHHHBBBB", dev)
    assert (length, kind, bcd_usb, ep0, vid, pid, nconf) == (18, 1, 0x200, 64, 0x1209, 2, 1)
    assert (imanu, iprod, iserial) == (1, 2, 3)
    config = f.configuration_descriptor()
    assert struct.unpack_from("<H", config, 2)[0] == len(config) == 9 + 9 + 3 * 7
    assert config[9 + 4] == 3  # bNumEndpoints
    assert f.string_descriptor(2, 0x0409)[2:].decode("utf-16-le") == f.product
    assert f.string_descriptor(9, 0x0409) is None
    assert f.control(0x80, 6, 0x0100, 0, 18) == dev


@pytest.mark.parametrize(("endpoint", "match"), [
    (lambda: Endpoint(0x00), "address"), (lambda: Endpoint(0x91), "address"),
    (lambda: Endpoint(0x81, "isochronous"), "transfer"),
    (lambda: Endpoint(0x81, "interrupt", interval=0), "interval"),
])
def test_bad_endpoints_are_refused(endpoint, match):
    with pytest.raises(ValueError, match=match):
        endpoint()


def test_bad_descriptor_fields_are_refused():
    f = LoopbackFunction()
    f.vendor_id = 0x10000
    with pytest.raises(ValueError, match="vendor_id"):
        f.validate()
    g = LoopbackFunction()
    g.endpoints = (Endpoint(0x81), Endpoint(0x81))
    with pytest.raises(ValueError, match="duplicate"):
        g.validate()


def test_ftdi_baud_divisors():
    assert divisor_to_baud(fp.BAUD_DIVISOR_9600) == pytest.approx(9600.0)
    assert divisor_to_baud(fp.BAUD_DIVISOR_FIRMWARE) == pytest.approx(3e6 / 21)
    assert divisor_to_baud(fp.BAUD_DIVISOR_NORMAL) == pytest.approx(1.5e6)


def test_ftdi_prefixes_status_bytes_honours_purge_and_latency():
    clock = FakeClock()
    f = EmulatedFalcon(firmware_loaded=True, homed=True, clock=clock)
    ctrl_out(f, fp.SIO_SET_LATENCY_TIMER, 16)
    assert f.in_(fp.EP_IN, 64) is None            # nothing, latency not yet expired
    clock.advance_ms(16)
    assert f.in_(fp.EP_IN, 64) == MODEM_STATUS     # status-only packet per latency period
    f.serial_to_host(b"x" * 100)
    first = f.in_(fp.EP_IN, 64)
    assert first[:2] == MODEM_STATUS and first[2:] == b"x" * 62
    ctrl_out(f, fp.SIO_RESET, fp.SIO_RESET_PURGE_RX)
    assert f.in_(fp.EP_IN, 64) is None
    f.serial_to_host(b"y" * 70)
    two_packets = f.in_(fp.EP_IN, 128)
    assert fp.strip_ftdi_status(two_packets) == b"y" * 70
    assert two_packets[64:66] == MODEM_STATUS
    assert f.control(fp.FTDI_REQUEST_OUT, 0x55, 0, 0, b"") is None   # unknown: STALL


# -- the Falcon's microcontroller, driven through its USB hooks ---------------------------


def falcon_cycle(f: EmulatedFalcon, motor=(0, 0, 0), homing=False) -> tuple:
    f.out(fp.EP_OUT, fp.encode_command(motor, fp.LED_BLUE, homing=homing))
    return fp.decode_status(fp.strip_ftdi_status(f.in_(fp.EP_IN, 64)))


def test_bootloader_needs_dtr_toggle_and_9600_then_echoes_the_upload():
    f = EmulatedFalcon()
    for req, val in ((fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_9600),
                     (fp.SIO_SET_DATA, fp.LINE_8N1)):
        ctrl_out(f, req, val)
    f.out(fp.EP_OUT, fp.FIRMWARE_PROBE)               # no reset yet: ignored
    assert not f.to_host and f.garbled_bytes == 3
    ctrl_out(f, fp.SIO_MODEM_CTRL, fp.MODEM_DTR_LOW)
    ctrl_out(f, fp.SIO_MODEM_CTRL, fp.MODEM_DTR_HIGH)
    f.out(fp.EP_OUT, fp.FIRMWARE_PROBE[:2])           # split across two writes
    f.out(fp.EP_OUT, fp.FIRMWARE_PROBE[2:])
    assert fp.strip_ftdi_status(f.in_(fp.EP_IN, 64)) == fp.FIRMWARE_PROBE_REPLY
    ctrl_out(f, fp.SIO_MODEM_CTRL, fp.MODEM_DTR_LOW)
    f.out(fp.EP_OUT, fp.FIRMWARE_UPLOAD_START)        # still 9600: not understood
    assert not f.to_host
    ctrl_out(f, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_FIRMWARE)
    f.out(fp.EP_OUT, fp.FIRMWARE_UPLOAD_START + b"\x01\x02")
    assert fp.strip_ftdi_status(f.in_(fp.EP_IN, 64)) == b"A\x01\x02"
    assert f.mode == "bootloader"
    ctrl_out(f, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL)
    assert f.mode == "firmware" and f.upload_bytes == 2
    counts, _buttons, homed = falcon_cycle(f)
    assert homed == (False, False, False) and counts == (0, 0, 0)  # relative until homed


def test_firmware_replies_once_per_packet_and_skips_garbage():
    f = EmulatedFalcon(firmware_loaded=True, homed=True, buttons=0x5)
    ctrl_out(f, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL)
    command = fp.encode_command((100, -200, 300), fp.LED_RED)
    f.out(fp.EP_OUT, b"\x00junk" + command[:7])
    f.out(fp.EP_OUT, command[7:] + command)
    payload = fp.strip_ftdi_status(f.in_(fp.EP_IN, 64))
    assert len(payload) == 2 * fp.PACKET_BYTES
    counts, buttons, homed = fp.decode_status(payload[:16])
    assert buttons == 0x5 and homed == (True, True, True)
    assert list(counts) == f.mechanism.encoder_counts().tolist()
    assert f.cycles == 2 and f.bad_packets == 1 and f.last_motor == (100, -200, 300)
    assert f.leds == fp.LED_RED
    ctrl_out(f, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_9600)   # wrong rate: garbled
    f.out(fp.EP_OUT, command)
    assert f.cycles == 2 and f.garbled_bytes == 16


def test_dtr_toggle_resets_to_the_bootloader_and_loses_homing():
    f = EmulatedFalcon(firmware_loaded=True, homed=True)
    ctrl_out(f, fp.SIO_MODEM_CTRL, fp.MODEM_DTR_HIGH)
    assert f.mode == "bootloader" and not f.firmware_loaded and f.homed == [False] * 3
    with pytest.raises(ValueError, match="homed needs firmware_loaded"):
        EmulatedFalcon(homed=True)


def test_homing_completes_after_enough_travel_and_makes_encoders_absolute():
    clock = FakeClock()
    f = EmulatedFalcon(firmware_loaded=True, clock=clock, homing_travel_counts=300)
    ctrl_out(f, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL)
    # Sweep the hand through the workspace; the grip follows it.
    path = [[0.0, 0, 0, 0], [0.3, 25, 0, 0], [0.6, -25, 0, 0], [0.9, 0, 25, 0],
            [1.2, 0, -25, 0], [1.5, 0, 0, 25], [1.8, 0, 0, -25], [2.1, 0, 0, 0]]
    f.commands()["set_hand"](path=path)
    homed = (False, False, False)
    for _ in range(2200):
        clock.advance_ms(1)
        counts, _b, homed = falcon_cycle(f, homing=True)
    assert homed == (True, True, True)
    assert list(counts) == f.mechanism.encoder_counts().tolist()


# -- the mechanism -----------------------------------------------------------------------


def test_a_motor_force_accelerates_the_grip_as_commanded():
    m = FalconMechanism(0, hand_on=False)
    force = np.array([0.0, 1.0, 2.0])
    cmd = torques_to_commands(motor_torques(m.p, force))
    m.command(0, tuple(int(c) for c in cmd))
    np.testing.assert_allclose(m.motor_force_N(), force, atol=2e-3)  # command quantization
    m.advance(20_000_000)   # 20 ms: x = F t² / 2m, friction a few % at most
    expected_mm = force / m.mass_kg * 0.02**2 / 2 * 1e3
    np.testing.assert_allclose(m.position_mm(), expected_mm, rtol=0.03, atol=1e-3)


@given(force=st.lists(st.floats(-9.0, 9.0), min_size=3, max_size=3),
       target=st.lists(st.floats(-57.0, 57.0), min_size=3, max_size=3),
       seconds=st.floats(0.001, 0.5))
def test_the_grip_stays_within_the_end_stops(force, target, seconds):
    m = FalconMechanism(0)
    m.set_path(0, [(0.0, target)])
    cmd = torques_to_commands(motor_torques(m.p, np.array(force)))
    m.command(0, tuple(int(c) for c in cmd))
    m.advance(int(seconds * 1e9))
    # The stops are stiff enough that even a full-force crash stays where the IK is valid.
    assert np.linalg.norm(m.position_mm()) <= WORKSPACE_RADIUS_M * 1e3 + 3.0
    assert np.all(np.isfinite(inverse_kinematics(m.p)))


# -- the board, driven through its USB hooks ---------------------------------------------


def board_status(b: EmulatedBoard) -> bp.Status | None:
    raw = b.in_(bp.EP_IN, 64)
    return None if raw is None else bp.decode_status(raw)


def test_board_applies_frames_rejects_bad_ones_and_latches_faults_once():
    clock = FakeClock()
    b = EmulatedBoard(clock=clock)
    assert board_status(b) is None                      # nothing queued: NAK
    b.out(bp.EP_OUT, bp.encode_frame(7, 250_000, 16384, ttl_ms=100))
    clock.advance_ms(2)
    s = board_status(b)
    assert (s.last_seq, s.output_on, s.level_q15, s.faults) == (7, True, 16384, 0)
    bad = bytearray(bp.encode_frame(8, 250_000, 1000))
    bad[-1] ^= 0xFF
    b.out(bp.EP_OUT, bytes(bad))
    b.out(bp.EP_OUT, b"short")                          # replaces the unread status
    s = board_status(b)
    assert s.last_seq == 7 and s.rejected == 2
    assert s.faults == bp.FAULT_BAD_CRC | bp.FAULT_BAD_LENGTH
    assert board_status(b) is None
    b.out(bp.EP_OUT, bp.encode_frame(9, 250_000, 16384, ttl_ms=100))
    assert board_status(b).faults == 0                  # latched faults were sent once
    frames = b.commands()["frames"]()
    assert [f["valid"] for f in frames] == [True, False, False, True]
    assert frames[1]["raw"] == bytes(bad).hex()


def test_board_ttl_silences_at_last_frame_plus_ttl():
    clock = FakeClock()
    b = EmulatedBoard(clock=clock)
    b.out(bp.EP_OUT, bp.encode_frame(1, 1_000_000, 30000, ttl_ms=20))
    t_frame = clock.t
    clock.advance_ms(500)                                # the host went quiet
    s = board_status(b)
    assert s.ttl_expired and not s.output_on and s.faults & bp.FAULT_TTL_EXPIRED
    assert s.level_q15 == 0
    log = b.commands()["output_log"]()
    assert log[-1]["reason"] == "ttl" and log[-1]["t_ns"] == t_frame + 20_000_000
    b.out(bp.EP_OUT, bp.encode_frame(2, 1_000_000, 30000, ttl_ms=20))
    assert not board_status(b).ttl_expired


# -- through real libusb: emulator process + preloaded client process ----------------------

needs_umockdev = pytest.mark.skipif(emulation_unavailable_reason() is not None,
                                    reason=f"USB emulation unavailable: "
                                           f"{emulation_unavailable_reason()}")

CLIENT_PRELUDE = """
import json, sys, time, errno
import usb.core, usb.util, libusb_package
backend = libusb_package.get_libusb1_backend()
def find(vid, pid):
    dev = usb.core.find(idVendor=vid, idProduct=pid, backend=backend)
    if dev is None:
        raise SystemExit("device not found")
    return dev
def emit(**kv):
    print(json.dumps(kv), flush=True)
"""


def run_client(emu: EmulatedUsb, body: str, *args: str, timeout_s: float = 120.0) -> dict:
    """Run ``body`` (after CLIENT_PRELUDE) under the emulator's preload; its last stdout line
    is JSON."""
    proc = subprocess.run([sys.executable, "-c", CLIENT_PRELUDE + body, *args],
                          env=emu.client_env(), capture_output=True, text=True,
                          timeout=timeout_s)
    assert proc.returncode == 0, f"client failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@contextlib.contextmanager
def interactive_client(emu: EmulatedUsb, script: str):
    """A client ``script`` under the emulator's preload that prints ``{"ready": ...}``, then
    waits on stdin before each step and reports it as a JSON line: yields ``(go, read)``;
    ``go()`` lets it take a step, ``read()`` returns its next report. Killed on the way out."""
    proc = subprocess.Popen([sys.executable, "-c", script], env=emu.client_env(),
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def go() -> None:
        proc.stdin.write("\n")
        proc.stdin.flush()

    def read() -> dict:
        return json.loads(proc.stdout.readline())

    try:
        assert read()["ready"]
        yield go, read
        assert proc.wait(30) == 0
    finally:
        proc.kill()


LOOPBACK_CLIENT = """
dev = find(0x1209, 0x0002)
dev.set_configuration()
out = {"strings": [dev.manufacturer, dev.product, dev.serial_number]}
out["stored"] = dev.ctrl_transfer(0x40, 1, 0, 0, b"hello")
out["loaded"] = bytes(dev.ctrl_transfer(0xC0, 2, 0, 0, 64)).decode()
try:
    dev.ctrl_transfer(0xC0, 3, 0, 0, 8)
except usb.core.USBError as exc:
    out["stall_errno"] = exc.errno
dev.write(0x01, b"ping")
out["echo"] = bytes(dev.read(0x81, 64, 1000)).decode()
t = time.monotonic()
try:
    dev.read(0x82, 64, 100)
except usb.core.USBTimeoutError:
    out["timeout_s"] = time.monotonic() - t
dev.write(0x01, b"after timeout")
out["echo2"] = bytes(dev.read(0x81, 64, 1000)).decode()
emit(**out)
"""


@needs_umockdev
def test_pyusb_drives_the_loopback_device_through_libusb():
    with EmulatedUsb("loopback") as emu:
        out = run_client(emu, LOOPBACK_CLIENT)
        stats = emu.control("stats")
    assert out["strings"] == ["burrforce", "usbfs loopback (emulated)", "LOOP0001"]
    assert out["stored"] == 5 and out["loaded"] == "hello"
    assert out["stall_errno"] == errno.EPIPE
    assert out["echo"] == "ping" and out["echo2"] == "after timeout"
    assert 0.09 <= out["timeout_s"] < 5.0
    assert stats["ioctls"]["DISCARDURB"] >= 1          # libusb cancelled the timed-out URB


PENDING_CLIENT = """
dev = find(0x1209, 0x0002)
dev.set_configuration()
emit(ready=True)
sys.stdin.readline()
data = bytes(dev.read(0x82, 64, 10000))
emit(pushed=data.hex(), t_ns=time.monotonic_ns())
sys.stdin.readline()
try:
    dev.read(0x82, 64, 10000)
    emit(error=None)
except usb.core.USBError as exc:
    t_fail = time.monotonic_ns()
    try:
        dev.write(0x01, b"x", 1000)
        next_errno = None
    except usb.core.USBError as exc2:
        next_errno = exc2.errno
    emit(error=exc.errno, t_ns=t_fail, next_errno=next_errno)
"""


@needs_umockdev
def test_a_pending_read_completes_on_data_and_fails_at_once_on_unplug():
    with EmulatedUsb("loopback") as emu, \
            interactive_client(emu, CLIENT_PRELUDE + PENDING_CLIENT) as (go, read):
        go()
        time.sleep(0.2)                              # the read is pending by now
        t_push = time.monotonic_ns()
        emu.control("push", data_hex="c0ffee")
        pushed = read()
        go()
        time.sleep(0.2)
        t_unplug = time.monotonic_ns()
        emu.unplug()
        failed = read()
    assert pushed["pushed"] == "c0ffee"
    assert (pushed["t_ns"] - t_push) * 1e-9 < 1.0      # answered on push, not on timeout
    assert failed["error"] == errno.ENODEV and failed["next_errno"] == errno.ENODEV
    assert (failed["t_ns"] - t_unplug) * 1e-9 < 1.0    # not the 10 s timeout


FALCON_CLIENT = """
from burrforce.server.devices.falcon import protocol as fp
dev = find(fp.VID, fp.PID)
dev.set_configuration()
usb.util.claim_interface(dev, fp.INTERFACE)
def ctrl(req, val):
    dev.ctrl_transfer(fp.FTDI_REQUEST_OUT, req, val, fp.FTDI_INDEX, None, fp.CONTROL_TIMEOUT_MS)
def payload(n):
    buf = b""
    deadline = time.monotonic() + 2.0
    while len(buf) < n and time.monotonic() < deadline:
        buf += fp.strip_ftdi_status(bytes(dev.read(fp.EP_IN, 64, 100)))
    return buf
out = {}
for req, val in ((fp.SIO_RESET, fp.SIO_RESET_PURGE_RX), (fp.SIO_RESET, fp.SIO_RESET_PURGE_TX),
                 (fp.SIO_SET_LATENCY_TIMER, fp.LATENCY_FIRMWARE_MS),
                 (fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_9600), (fp.SIO_SET_DATA, fp.LINE_8N1),
                 (fp.SIO_SET_FLOW_CTRL, fp.FLOW_CONTROL_OFF),
                 (fp.SIO_MODEM_CTRL, fp.MODEM_RTS_LOW)):
    ctrl(req, val)
if sys.argv[1]:   # reset into the bootloader: DTR low, then high
    ctrl(fp.SIO_MODEM_CTRL, fp.MODEM_DTR_LOW)
    ctrl(fp.SIO_MODEM_CTRL, fp.MODEM_DTR_HIGH)
image = bytes.fromhex(sys.argv[1])
if image:
    dev.write(fp.EP_OUT, fp.FIRMWARE_PROBE)
    out["probe_reply"] = payload(4).hex()
    ctrl(fp.SIO_MODEM_CTRL, fp.MODEM_DTR_LOW)
    ctrl(fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_FIRMWARE)
    dev.write(fp.EP_OUT, fp.FIRMWARE_UPLOAD_START)
    out["start_echo"] = payload(1).hex()
    echo = b""
    for i in range(0, len(image), fp.FIRMWARE_CHUNK_BYTES):
        chunk = image[i:i + fp.FIRMWARE_CHUNK_BYTES]
        dev.write(fp.EP_OUT, chunk)
        echo += payload(len(chunk))
    out["echo_ok"] = echo == image
ctrl(fp.SIO_SET_LATENCY_TIMER, fp.LATENCY_NORMAL_MS)
ctrl(fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL)
ctrl(fp.SIO_RESET, fp.SIO_RESET_PURGE_RX)
n = int(sys.argv[2])
encoders = []
t0 = time.perf_counter()
for i in range(n):
    dev.write(fp.EP_OUT, fp.encode_command((0, 0, 0), fp.LED_GREEN))
    counts, buttons, homed = fp.decode_status(payload(fp.PACKET_BYTES))
    encoders.append(counts)
out["s_per_cycle"] = (time.perf_counter() - t0) / n
out["encoders"] = encoders
out["buttons"] = buttons
out["homed"] = homed
emit(**out)
"""


@needs_umockdev
def test_pyusb_loads_firmware_into_an_emulated_falcon_then_cycles_it():
    image = bytes(range(256)) + b"\x5a" * 44          # 300 bytes: 5 chunks, a short last one
    with EmulatedUsb("falcon", start_mm=[6.0, -4.0, 9.0]) as emu:
        assert emu.state()["mode"] == "bootloader"
        out = run_client(emu, FALCON_CLIENT, image.hex(), "20")
        state = emu.state()
    assert out["probe_reply"] == fp.FIRMWARE_PROBE_REPLY.hex() and out["start_echo"] == "41"
    assert out["echo_ok"]
    assert state["mode"] == "firmware" and state["upload_bytes"] == len(image)
    assert state["upload_sha256"] == hashlib.sha256(image).hexdigest()
    ftdi = state["ftdi"]
    assert ftdi["latency_ms"] == 1 and ftdi["baud"] == 1.5e6 and ftdi["events"]["dtr_rise"] == 1
    assert state["cycles"] == 20 and state["bad_packets"] == 0
    # Fresh firmware is unhomed: encoders count from where the grip was at the reset.
    assert out["homed"] == [False, False, False]
    assert out["encoders"][-1] == [0, 0, 0]


@needs_umockdev
def test_emulated_falcon_encoders_are_the_mechanism_s(record_property):
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True, start_mm=[6.0, -4.0, 9.0],
                     buttons=0x2) as emu:
        out = run_client(emu, FALCON_CLIENT, "", "200")
        state = emu.state()
        log = emu.control("log")
    assert state["cycles"] == 200 and state["bad_packets"] == 0
    # What the client decoded is what the emulator logged it sent, cycle by cycle ...
    assert [row[4:7] for row in log["rows"]] == [list(e) for e in out["encoders"]]
    assert out["buttons"] == 0x2 and out["homed"] == [True, True, True]
    # ... and those encoders are the mechanism's: IK of the true grip position, quantized.
    true_counts = np.rint(angle_to_encoder(inverse_kinematics(np.array(state["position_m"]))))
    assert out["encoders"][-1] == true_counts.astype(int).tolist()
    p, converged = forward_kinematics(encoder_to_angle(np.array(out["encoders"][-1], float)),
                                      np.array(state["position_m"]))
    assert converged
    assert np.linalg.norm(p - np.array(state["position_m"])) * 1e3 < 0.2  # one count ≈ 0.06 mm
    np.testing.assert_allclose(state["position_mm"], [6.0, -4.0, 9.0], atol=0.05)
    record_property("emulated_falcon_ms_per_cycle", round(out["s_per_cycle"] * 1e3, 3))
    print(f"\nemulated Falcon I/O cycle (pyusb write + read): {out['s_per_cycle'] * 1e3:.2f} ms")


FORCE_CLIENT = """
from burrforce.server.devices.falcon import protocol as fp
dev = find(fp.VID, fp.PID)
dev.set_configuration()
dev.ctrl_transfer(fp.FTDI_REQUEST_OUT, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL, 0, None)
def cycle(motor):
    dev.write(fp.EP_OUT, fp.encode_command(motor))
    buf = b""
    while len(buf) < fp.PACKET_BYTES:
        buf += fp.strip_ftdi_status(bytes(dev.read(fp.EP_IN, 64, 500)))
    return fp.decode_status(buf)[0]
motor = tuple(int(v) for v in sys.argv[1:4])
t_end = time.monotonic() + 0.15
while time.monotonic() < t_end:
    cycle(motor)
t_zero = time.monotonic_ns()
for _ in range(5):
    cycle((0, 0, 0))
emit(t_zero_ns=t_zero)
"""


@needs_umockdev
def test_commanded_motor_torques_push_the_emulated_grip():
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True, hand=False) as emu:
        p = np.array(emu.state()["position_m"])
        force = np.array([0.0, 0.0, 1.5])
        motor = torques_to_commands(motor_torques(p, force))
        np.testing.assert_allclose(emu.control("force_at", motor=motor.tolist()), force,
                                   atol=2e-3)
        out = run_client(emu, FORCE_CLIENT, *(str(int(m)) for m in motor))
        state = emu.state()
        rows = emu.control("log")["rows"]
    assert state["position_mm"][2] > 5.0              # 1.5 N on 0.25 kg for ≥ 0.15 s
    assert abs(state["position_mm"][0]) < 0.5 and abs(state["position_mm"][1]) < 0.5
    first_zero = next(r for r in rows if r[1:4] == [0, 0, 0])
    assert all(r[1:4] == [int(m) for m in motor] for r in rows[:rows.index(first_zero)])
    # The log times each command: the zero arrived within 50 ms of the client sending it.
    assert 0 <= first_zero[0] - out["t_zero_ns"] < 50_000_000
    assert state["motor_command"] == [0, 0, 0]


UNPLUG_CLIENT = """
from burrforce.server.devices.falcon import protocol as fp
dev = find(fp.VID, fp.PID)
dev.set_configuration()
dev.ctrl_transfer(fp.FTDI_REQUEST_OUT, fp.SIO_SET_BAUD_RATE, fp.BAUD_DIVISOR_NORMAL, 0, None)
n = 0
try:
    while True:
        dev.write(fp.EP_OUT, fp.encode_command((0, 0, 0)), 1000)
        buf = b""
        while len(buf) < fp.PACKET_BYTES:
            buf += fp.strip_ftdi_status(bytes(dev.read(fp.EP_IN, 64, 1000)))
        n += 1
        if n == 50:
            emit(cycling=True)
except usb.core.USBError as exc:
    emit(errno=exc.errno, t_ns=time.monotonic_ns(), cycles=n)
"""


@needs_umockdev
def test_unplugging_the_falcon_fails_the_next_transfer_with_enodev():
    with EmulatedUsb("falcon", firmware_loaded=True, homed=True) as emu:
        proc = subprocess.Popen([sys.executable, "-c", CLIENT_PRELUDE + UNPLUG_CLIENT],
                                env=emu.client_env(), stdout=subprocess.PIPE, text=True)
        try:
            assert json.loads(proc.stdout.readline())["cycling"]
            t_unplug = time.monotonic_ns()
            emu.unplug()
            failed = json.loads(proc.stdout.readline())
            assert proc.wait(30) == 0
        finally:
            proc.kill()
        assert failed["errno"] == errno.ENODEV
        assert (failed["t_ns"] - t_unplug) * 1e-9 < 1.0
        assert failed["cycles"] >= 50
        assert emu.control("stats")["unplugged"]
        # A process started after the unplug does not find the device.
        gone = subprocess.run([sys.executable, "-c", CLIENT_PRELUDE +
                               "emit(found=usb.core.find(idVendor=0x0403, idProduct=0xcb48, "
                               "backend=backend) is not None)"],
                              env=emu.client_env(), capture_output=True, text=True, timeout=60)
    assert json.loads(gone.stdout.strip().splitlines()[-1]) == {"found": False}


BOARD_CLIENT = """
from burrforce.server.devices.actuators import board_protocol as bp
dev = find(bp.VID, bp.PID)
dev.set_configuration()
sent, statuses = [], []
for seq in range(1, 21):
    frame = bp.encode_frame(seq, bp.frequency_to_mhz(200.0 + seq), bp.amplitude_to_q15(0.5),
                            ttl_ms=20)
    dev.write(bp.EP_OUT, frame)
    sent.append(frame.hex())
    statuses.append(bp.decode_status(bytes(dev.read(bp.EP_IN, 64, 500))).last_seq)
    time.sleep(0.002)
t_last = time.monotonic_ns()
time.sleep(0.1)
try:
    dev.read(bp.EP_IN, 64, 50)
    nak = False
except usb.core.USBTimeoutError:
    nak = True
dev.write(bp.EP_OUT, bp.encode_frame(21, 0, 0, on=False))
final = bp.decode_status(bytes(dev.read(bp.EP_IN, 64, 500)))
emit(sent=sent, statuses=statuses, t_last_ns=t_last, nak=nak,
     final=[final.state, final.faults, final.last_seq])
"""


@needs_umockdev
def test_the_emulated_board_records_frames_byte_for_byte_and_its_ttl():
    with EmulatedUsb("board") as emu:
        out = run_client(emu, BOARD_CLIENT)
        frames = emu.control("frames")
        output = emu.control("output_log")
    assert [f["raw"] for f in frames[:20]] == out["sent"]
    assert all(f["valid"] for f in frames)
    assert out["statuses"] == list(range(1, 21)) and out["nak"]
    state_bits, faults, last_seq = out["final"]
    assert faults & bp.FAULT_TTL_EXPIRED and last_seq == 21 and state_bits == 0
    ttl = [o for o in output if o["reason"] == "ttl"]
    assert ttl and all(o["amplitude_q15"] == 0 for o in ttl)
    # Silent exactly one TTL after the last frame, which left the client before t_last.
    assert ttl[-1]["t_ns"] == frames[19]["t_ns"] + 20_000_000
    assert ttl[-1]["t_ns"] - out["t_last_ns"] < 20_000_000
    # An earlier expiry is a real gap (a busy machine held the client longer than the TTL
    # between two frames): exactly one TTL after the frame before it, and the stream resumed.
    times = [f["t_ns"] for f in frames[:20]]
    for o in ttl[:-1]:
        assert o["t_ns"] == max(t for t in times if t <= o["t_ns"]) + 20_000_000, o
        assert any(t > o["t_ns"] for t in times), o


@needs_umockdev
def test_launcher_reports_bad_kinds_options_and_commands():
    with pytest.raises(ValueError, match="unknown emulated device"):
        EmulatedUsb("joystick")
    with pytest.raises(RuntimeError, match="warp_speed"):
        EmulatedUsb("falcon", warp_speed=9).start()
    with EmulatedUsb("loopback") as emu:
        with pytest.raises(EmulatorCommandError, match="unknown command"):
            emu.control("self_destruct")
        with pytest.raises(EmulatorCommandError, match="TypeError"):
            emu.control("push", bogus=1)
        assert "push" in emu.control("commands")
        with pytest.raises(RuntimeError, match="start the emulator"):
            EmulatedUsb("board").client_env()


def test_emulator_help_runs_without_umockdev():
    proc = subprocess.run([sys.executable, "-m", "support.emulation", "--help"],
                          capture_output=True, text=True, timeout=60,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.returncode == 0 and "falcon" in proc.stdout


REPLUG_CLIENT = """
dev = find(0x1209, 0x0002)
dev.set_configuration()
dev.write(0x01, b"before")
out = {"before": bytes(dev.read(0x81, 64, 1000)).decode()}
emit(ready=True)
sys.stdin.readline()                      # unplugged, then plugged back in
try:
    dev.write(0x01, b"stale handle", 1000)
except usb.core.USBError as exc:
    out["stale_errno"] = exc.errno
usb.util.dispose_resources(dev)
dev = find(0x1209, 0x0002)
dev.set_configuration()
dev.write(0x01, b"after")
out["after"] = bytes(dev.read(0x81, 64, 1000)).decode()
emit(**out)
"""


@needs_umockdev
def test_replug_serves_a_fresh_open_while_old_handles_stay_dead():
    with EmulatedUsb("loopback") as emu, \
            interactive_client(emu, CLIENT_PRELUDE + REPLUG_CLIENT) as (go, read):
        emu.unplug()
        emu.replug()
        go()
        out = read()
    assert out == {"before": "before", "stale_errno": errno.ENODEV, "after": "after"}
