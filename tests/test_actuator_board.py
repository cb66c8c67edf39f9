"""The vibration board's wire protocol (round trips, CRC, every rejection) and the USB
driver against the emulated board (umockdev; skipped where umockdev is missing)."""

from __future__ import annotations

import itertools
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.actuators import board_protocol as bp

# -- CRC ---------------------------------------------------------------------------------------


def test_crc_check_value():
    assert bp.crc16_ccitt_false(bp.CRC_CHECK_INPUT) == bp.CRC_CHECK_VALUE == 0x29B1


def test_crc_known_vectors():
    assert bp.crc16_ccitt_false(b"") == 0xFFFF  # init, no xorout
    assert bp.crc16_ccitt_false(b"A") == 0xB915
    # incremental use: CRC of a concatenation continues from the first part's CRC
    assert bp.crc16_ccitt_false(b"6789", bp.crc16_ccitt_false(b"12345")) == 0x29B1


@given(st.binary(max_size=64))
def test_crc_matches_a_bitwise_reference(data):
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    assert bp.crc16_ccitt_false(data) == crc


# -- frames ------------------------------------------------------------------------------------

frame_args = st.fixed_dictionaries({
    "seq": st.integers(0, 0xFFFF),
    "frequency_mhz": st.integers(0, bp.FREQUENCY_MAX_MHZ),
    "amplitude_q15": st.integers(0, bp.AMPLITUDE_Q15_MAX),
    "on": st.booleans(),
    "am": st.booleans(),
    "ttl_ms": st.integers(bp.TTL_MIN_MS, bp.TTL_MAX_MS),
})


@given(frame_args, st.integers(bp.AM_HZ_MIN, bp.AM_HZ_MAX))
def test_frame_round_trip(args, am_hz):
    am_hz = am_hz if args["am"] else 0
    data = bp.encode_frame(**args, am_hz=am_hz)
    assert len(data) == bp.FRAME_SIZE == 18
    frame = bp.decode_frame(data)
    assert frame == bp.Frame(**args, am_hz=am_hz)
    assert bp.encode(frame) == data


def test_frame_bytes_are_the_documented_layout():
    data = bp.encode_frame(seq=0x1234, frequency_mhz=1_000_000, amplitude_q15=16384, on=True,
                           am=True, ttl_ms=50)
    # magic "BV", version 1, flags ON|AM, seq, ttl 50, 1 kHz in mHz, Q15 0.5, AM 250 Hz, CRC
    assert data[:16] == bytes.fromhex("42560103" "3412" "3200" "40420f00" "0040" "fa00")
    assert data[16:] == struct.pack("<H", bp.crc16_ccitt_false(data[:16]))
    assert data.hex() == "4256010334123200" "40420f000040fa00" + data[16:].hex()


def test_seq_wraps_and_defaults():
    frame = bp.decode_frame(bp.encode_frame(seq=0x10001, frequency_mhz=250_000,
                                            amplitude_q15=100))
    assert frame.seq == 1 and frame.on and not frame.am and frame.am_hz == 0
    assert frame.ttl_ms == bp.TTL_DEFAULT_MS
    assert frame.frequency_hz == 250.0 and frame.amplitude == pytest.approx(100 / 32767)
    assert frame.audible
    assert not bp.decode_frame(bp.encode_frame(1, 250_000, 100, on=False)).audible
    assert bp.decode_frame(bp.encode_frame(1, 250_000, 100, am=True)).am_hz == bp.AM_HZ_DEFAULT


def _valid() -> bytes:
    return bp.encode_frame(seq=7, frequency_mhz=300_000, amplitude_q15=20_000, on=True)


def _recrc(body: bytes) -> bytes:
    return body[:16] + struct.pack("<H", bp.crc16_ccitt_false(body[:16]))


@pytest.mark.parametrize(("data", "fault", "words"), [
    (_valid()[:-1], bp.FAULT_BAD_LENGTH, "length 17"),
    (_valid() + b"\0", bp.FAULT_BAD_LENGTH, "length 19"),
    (b"", bp.FAULT_BAD_LENGTH, "length 0"),
    (_recrc(b"BX" + _valid()[2:]), bp.FAULT_BAD_MAGIC, "magic"),
    (_recrc(_valid()[:2] + b"\x02" + _valid()[3:]), bp.FAULT_BAD_VERSION, "version 2"),
    (_valid()[:-2] + bytes([_valid()[-2] ^ 1, _valid()[-1]]), bp.FAULT_BAD_CRC, "CRC"),
    (_valid()[:9] + bytes([_valid()[9] ^ 0x40]) + _valid()[10:], bp.FAULT_BAD_CRC, "CRC"),
    (_recrc(_valid()[:3] + b"\x05" + _valid()[4:]), bp.FAULT_BAD_VALUE, "reserved flag"),
    (_recrc(_valid()[:6] + struct.pack("<H", 0) + _valid()[8:]), bp.FAULT_BAD_VALUE, "ttl"),
    (_recrc(_valid()[:6] + struct.pack("<H", 1001) + _valid()[8:]), bp.FAULT_BAD_VALUE, "ttl"),
    (_recrc(_valid()[:8] + struct.pack("<I", bp.FREQUENCY_MAX_MHZ + 1) + _valid()[12:]),
     bp.FAULT_BAD_VALUE, "frequency"),
    (_recrc(_valid()[:12] + struct.pack("<H", 32768) + _valid()[14:]),
     bp.FAULT_BAD_VALUE, "amplitude"),
    (_recrc(_valid()[:14] + struct.pack("<H", 250) + _valid()[16:]),
     bp.FAULT_BAD_VALUE, "am_hz must be 0"),
    (_recrc(_valid()[:3] + b"\x03" + _valid()[4:14] + struct.pack("<H", 0) + _valid()[16:]),
     bp.FAULT_BAD_VALUE, "am_hz must be 1"),
])
def test_every_bad_frame_is_named(data, fault, words):
    with pytest.raises(bp.ProtocolError, match=words) as info:
        bp.decode_frame(data)
    assert info.value.fault == fault
    assert isinstance(info.value, ValueError)


@given(st.binary(min_size=bp.FRAME_SIZE, max_size=bp.FRAME_SIZE))
def test_random_bytes_decode_or_raise_protocol_error(data):
    try:
        frame = bp.decode_frame(data)
    except bp.ProtocolError as exc:
        assert exc.fault in bp.FAULT_NAMES
    else:
        assert bp.encode(frame) == data


@given(frame_args, st.integers(0, bp.FRAME_SIZE * 8 - 1))
def test_any_single_bit_flip_is_rejected(args, bit):
    data = bytearray(bp.encode_frame(**args))
    data[bit // 8] ^= 1 << (bit % 8)
    with pytest.raises(bp.ProtocolError):
        bp.decode_frame(bytes(data))


@pytest.mark.parametrize("kwargs", [
    dict(seq=0, frequency_mhz=-1, amplitude_q15=0),
    dict(seq=0, frequency_mhz=0, amplitude_q15=40_000),
    dict(seq=0, frequency_mhz=0, amplitude_q15=0, ttl_ms=0),
    dict(seq=0, frequency_mhz=0, amplitude_q15=0, am=True, am_hz=2000),
    dict(seq=0, frequency_mhz=0, amplitude_q15=0, am=False, am_hz=250),
])
def test_encode_rejects_out_of_range(kwargs):
    with pytest.raises(ValueError):
        bp.encode_frame(**kwargs)


def test_unit_conversions():
    assert bp.frequency_to_mhz(1000.0) == 1_000_000
    assert bp.frequency_to_mhz(0.0004) == 0
    assert bp.amplitude_to_q15(1.0) == 32767 and bp.amplitude_to_q15(0.5) == 16384
    for bad in (-1.0, float("nan"), 20_000.1):
        with pytest.raises(ValueError):
            bp.frequency_to_mhz(bad)
    for bad in (-0.01, 1.01, float("inf")):
        with pytest.raises(ValueError):
            bp.amplitude_to_q15(bad)


# -- status ------------------------------------------------------------------------------------


@given(st.integers(0, 0xFFFF), st.integers(0, bp.STATES_KNOWN), st.integers(0, 0xFFFF),
       st.integers(0, 2**40), st.integers(0, 2**20), st.integers(0, bp.AMPLITUDE_Q15_MAX))
def test_status_round_trip(last_seq, state, faults, underruns, rejected, level):
    data = bp.encode_status(last_seq, state, faults, underruns, rejected, level)
    assert len(data) == bp.STATUS_SIZE == 18
    status = bp.decode_status(data)
    assert status == bp.Status(last_seq, state, faults, underruns & 0xFFFFFFFF,
                               rejected & 0xFFFF, level)


def test_status_layout_and_fault_names():
    data = bp.encode_status(last_seq=0x0102, state=bp.STATE_OUTPUT_ON,
                            faults=bp.FAULT_BAD_CRC | bp.FAULT_TTL_EXPIRED | 0x8000,
                            underruns=3, rejected=2, level_q15=32767)
    assert data[:16] == bytes.fromhex("42530101" "0201" "2880" "03000000" "0200" "ff7f")
    status = bp.decode_status(data)
    assert status.output_on and not status.ttl_expired and status.level == 1.0
    assert status.fault_names() == ["bad CRC", "TTL expired", "bit 15"]


@pytest.mark.parametrize(("mutate", "words"), [
    (lambda d: d[:-1], "length"),
    (lambda d: _recrc(b"BV" + d[2:]), "magic"),
    (lambda d: _recrc(d[:2] + b"\x09" + d[3:]), "version"),
    (lambda d: d[:-1] + bytes([d[-1] ^ 0xFF]), "CRC"),
    (lambda d: _recrc(d[:14] + struct.pack("<H", 40_000) + d[16:]), "level"),
])
def test_bad_status_is_named(mutate, words):
    with pytest.raises(bp.ProtocolError, match=words):
        bp.decode_status(mutate(bp.encode_status(1)))


def test_encode_status_rejects_out_of_range():
    for kwargs in (dict(last_seq=70_000), dict(last_seq=0, state=0x80),
                   dict(last_seq=0, level_q15=40_000), dict(last_seq=0, faults=-1)):
        with pytest.raises(ValueError):
            bp.encode_status(**kwargs)


def test_constants():
    assert (bp.VID, bp.PID) == (0x1209, 0x0001)
    assert (bp.EP_OUT, bp.EP_IN, bp.INTERFACE_CLASS) == (0x01, 0x81, 0xFF)
    assert bp.FRAME_SIZE <= bp.MAX_PACKET_SIZE and bp.STATUS_SIZE <= bp.MAX_PACKET_SIZE


# -- the USB driver against the emulated board -------------------------------------------------

try:
    from support.emulation.launcher import (
        EmulatedUsb,
        emulation_unavailable_reason,
    )
except ImportError as exc:  # pragma: no cover - the emulation package ships with burrforce
    EmulatedUsb = None
    _EMULATION_REASON: str | None = f"emulation package missing: {exc}"
else:
    _EMULATION_REASON = emulation_unavailable_reason()

needs_emulation = pytest.mark.skipif(_EMULATION_REASON is not None,
                                     reason=f"USB emulation unavailable: {_EMULATION_REASON}")

DRIVER_PRELUDE = """
import json, sys, time
from burrforce.server.devices.actuators.synth import Perceptual
from burrforce.server.devices.actuators.usb_board import UsbBoardActuator
from burrforce.server.devices.base import DeviceError
def emit(**kv):
    print(json.dumps(kv), flush=True)
def stream(act, amplitude_N, hz, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        act.update(amplitude_N, hz)
        time.sleep(0.001)
"""

STREAM_DRIVER = """
act = UsbBoardActuator(serial="EMUBOARD1", full_scale_N=1.0, perceptual=Perceptual("am"))
with act:
    stream(act, 0.5, 300.0, 0.3)
    stream(act, 0.8, 1200.0, 0.1)     # above the 800 Hz corner: the AM flag
    t_last = time.monotonic_ns()      # the stream stops here
    time.sleep(0.15)
    stopped = dict(frames=act.frames_sent, updates=act.stats.updates)
    stream(act, 0.2, 150.0, 0.05)     # revives after the TTL expired
    time.sleep(0.01)
    faults_seen, status = act.faults_seen, act.status
emit(t_last_ns=t_last, stopped=stopped, faults_seen=faults_seen, frames=act.frames_sent,
     status=None if status is None else [status.last_seq, status.state, status.underruns],
     last_frame=act.last_frame.hex())
"""


def _run_driver(emu, body: str, timeout_s: float = 120.0) -> dict:
    import json
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", DRIVER_PRELUDE + body],
                          env=emu.client_env(), capture_output=True, text=True,
                          timeout=timeout_s)
    assert proc.returncode == 0, f"driver failed ({proc.returncode}):\n{proc.stderr[-4000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@needs_emulation
def test_usb_board_frames_byte_for_byte_and_silence_after_a_stopped_stream():
    with EmulatedUsb("board") as emu:
        out = _run_driver(emu, STREAM_DRIVER)
        frames = emu.control("frames")
        output = emu.control("output_log")
    assert frames and all(f["valid"] for f in frames), [f for f in frames if not f["valid"]]
    # Byte for byte: seq counts up from 0; every other field is what the updates asked for.
    q15 = bp.amplitude_to_q15
    phases = {(q15(0.5), 300_000, False), (q15(0.8), 1_200_000, True),
              (q15(0.2), 150_000, False), (0, 0, False)}
    for i, f in enumerate(frames):
        fr = f["frame"]
        assert fr["seq"] == i
        assert (fr["amplitude_q15"], fr["frequency_mhz"], fr["am"]) in phases
        assert fr["on"] == (fr["amplitude_q15"] > 0)
        expected = bp.encode_frame(i, fr["frequency_mhz"], fr["amplitude_q15"], on=fr["on"],
                                   am=fr["am"], ttl_ms=fr["ttl_ms"],
                                   am_hz=250 if fr["am"] else 0)
        assert bytes.fromhex(f["raw"]) == expected
        assert 1 <= fr["ttl_ms"] <= 50 - bp.RAMP_MAX_MS - 1
    assert frames[-1]["raw"] == out["last_frame"]
    # Rate-limited: not one frame per update, a keep-alive about every 25 ms while unchanged.
    t = [f["t_ns"] for f in frames]
    streaming = [b - a for a, b in itertools.pairwise(t) if b < out["t_last_ns"]]
    assert max(streaming) < 45_000_000  # the board's TTL never ran out mid-stream
    assert 10 <= out["stopped"]["frames"] <= 40 < out["stopped"]["updates"]
    # Stopped stream: the board's own TTL silences it within 50 ms of the last update.
    ttl = [o for o in output if o["reason"] == "ttl"]
    assert len(ttl) == 1 and ttl[0]["amplitude_q15"] == 0
    silent_ns = ttl[0]["t_ns"] + bp.RAMP_MAX_MS * 1_000_000
    print(f"silent {(silent_ns - out['t_last_ns']) / 1e6:.1f} ms after the last update")
    assert silent_ns - out["t_last_ns"] <= 50_000_000
    assert not [o for o in output if o["reason"] == "ttl" and o["t_ns"] < out["t_last_ns"]]
    # Revived, then closed with an explicit off frame; the status reported the TTL expiry.
    assert out["faults_seen"] & bp.FAULT_TTL_EXPIRED
    last = frames[-1]["frame"]
    assert not last["on"] and last["amplitude_q15"] == 0
    assert output[-1]["amplitude_q15"] == 0 and output[-1]["reason"] == "frame"
    assert out["status"] is not None and out["status"][2] == 0


UNPLUG_DRIVER = """
act = UsbBoardActuator()
act.open()
stream(act, 0.5, 300.0, 0.1)
emit(ready=True)
sys.stdin.readline()                    # the board is unplugged now
error = None
end = time.monotonic() + 5.0
while time.monotonic() < end:
    try:
        act.update(0.5, 300.0 + (time.monotonic() % 1.0))   # changing: a frame each time
    except DeviceError as exc:
        error = [type(exc).__name__, str(exc)]
        break
    time.sleep(0.001)
act.close()
emit(error=error)
"""


@needs_emulation
def test_usb_board_unplug_is_reported_as_disconnected():
    from test_devices_emulation import interactive_client

    with EmulatedUsb("board") as emu, \
            interactive_client(emu, DRIVER_PRELUDE + UNPLUG_DRIVER) as (go, read):
        emu.unplug()
        go()
        result = read()
    assert result["error"] is not None
    name, message = result["error"]
    assert name == "DeviceDisconnected", message
    assert "went away" in message


NOT_FOUND_DRIVER = """
try:
    UsbBoardActuator(serial="NO-SUCH-BOARD").open()
    emit(error=None)
except DeviceError as exc:
    emit(error=[type(exc).__name__, str(exc)])
"""


@needs_emulation
def test_usb_board_wrong_serial_is_not_found():
    with EmulatedUsb("board") as emu:
        out = _run_driver(emu, NOT_FOUND_DRIVER)
    name, message = out["error"]
    assert name == "DeviceNotFound" and "NO-SUCH-BOARD" in message and "1209:0001" in message


def test_usb_board_rejects_bad_settings():
    from burrforce.server.devices.actuators.usb_board import UsbBoardActuator

    with pytest.raises(ValueError, match="max_rate_hz"):
        UsbBoardActuator(max_rate_hz=5000.0)
    with pytest.raises(ValueError, match="watchdog"):
        UsbBoardActuator(watchdog_ms=5.0)
