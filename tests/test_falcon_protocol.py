"""The Falcon's 16-byte packets and the FTDI status stripping."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from burrforce.server.devices.falcon import protocol as P

int16 = st.integers(min_value=-32768, max_value=32767)
triples = st.tuples(int16, int16, int16)


def test_known_packet_matches_the_documented_bytes():
    # The reply seen in the research emulation decoded to encoders (100, -200, 300).
    assert P.encode_status([100, -200, 300]) == b"<EGAAIDPPMCBAAA>"
    assert P.decode_status(b"<EGAAIDPPMCBAAA>") == ((100, -200, 300), 0, (False,) * 3)


def test_command_flags_byte_layout():
    packet = P.encode_command([0, 0, 0], leds=P.LED_GREEN | P.LED_RED, homing=True)
    assert len(packet) == P.PACKET_BYTES
    assert packet[0:1] == b"<" and packet[-1:] == b">"
    assert packet[13] - 0x41 == P.LED_GREEN | P.LED_RED | P.HOMING_BIT
    assert packet[14] == 0x41
    # Least-significant nibble first.
    assert P.encode_command([0x1234, 0, 0])[1:5] == bytes([0x41 + 4, 0x41 + 3, 0x41 + 2, 0x41 + 1])


@given(triples, st.sampled_from([0, P.LED_GREEN, P.LED_BLUE, P.LED_RED, P.LED_MASK]),
       st.booleans())
def test_command_round_trip(motors, leds, homing):
    packet = P.encode_command(motors, leds=leds, homing=homing)
    assert len(packet) == 16
    assert all(0x41 <= b <= 0x50 for b in packet[1:15])
    assert P.decode_command(packet) == (motors, leds, homing)


@given(triples, st.integers(0, 15), st.tuples(st.booleans(), st.booleans(), st.booleans()))
def test_status_round_trip(encoders, buttons, homed):
    packet = P.encode_status(encoders, buttons=buttons, homed=homed)
    assert P.decode_status(packet) == (encoders, buttons, homed)


@pytest.mark.parametrize("bad", [[32768, 0, 0], [0, -32769, 0], [0, 0], [0, 0, 0, 0], [0.5, 0, 0],
                                 ["x", 0, 0]])
def test_encode_rejects_values_outside_int16(bad):
    with pytest.raises(ValueError):
        P.encode_command(bad)
    with pytest.raises(ValueError):
        P.encode_status(bad)


def test_encode_rejects_unknown_bits():
    with pytest.raises(ValueError, match="LED"):
        P.encode_command([0, 0, 0], leds=0x1)  # the homing bit is not an LED
    with pytest.raises(ValueError, match="button"):
        P.encode_status([0, 0, 0], buttons=0x10)
    with pytest.raises(ValueError, match="homed"):
        P.encode_status([0, 0, 0], homed=(True,))


GOOD = P.encode_status([1, 2, 3], 1, (True, True, True))


@pytest.mark.parametrize("bad, message", [
    (GOOD[:15], "16 bytes"),
    (GOOD + b"A", "16 bytes"),
    (b"", "16 bytes"),
    (b"[" + GOOD[1:], "framed"),
    (GOOD[:15] + b"]", "framed"),
    (GOOD[:3] + b"\x40" + GOOD[4:], "byte 3"),
    (GOOD[:5] + b"Z" + GOOD[6:], "byte 5"),
    (GOOD[:14] + b"\x00" + GOOD[15:], "byte 14"),
    (GOOD[:13] + b"\x30" + GOOD[14:], "flags"),
])
def test_decoders_reject_bad_frames(bad, message):
    with pytest.raises(ValueError, match=message):
        P.decode_status(bad)
    with pytest.raises(ValueError):
        P.decode_command(bad)


def test_decode_command_rejects_status_flags():
    # A status byte with homed flags is beyond the command's 4-bit flags field.
    with pytest.raises(ValueError, match="flags"):
        P.decode_command(GOOD)


def test_decoders_reject_non_bytes():
    with pytest.raises(ValueError, match="bytes"):
        P.decode_status("<EGAAIDPPMCBAAA>")  # type: ignore[arg-type]


@given(st.binary(min_size=0, max_size=400), st.sampled_from([8, 64]))
def test_strip_ftdi_status_drops_two_bytes_per_usb_packet(payload, max_packet):
    chunk = max_packet - P.FTDI_STATUS_BYTES
    pieces = [payload[i:i + chunk] for i in range(0, len(payload), chunk)] or [b""]
    raw = b"".join(b"\x31\x60" + piece for piece in pieces)
    assert P.strip_ftdi_status(raw, max_packet) == payload


def test_strip_ftdi_status_of_a_status_only_read_is_empty():
    assert P.strip_ftdi_status(b"\x31\x60") == b""
    assert P.strip_ftdi_status(b"") == b""
    with pytest.raises(ValueError):
        P.strip_ftdi_status(b"abc", max_packet=2)


def test_baud_divisors_give_the_documented_rates():
    def rate(divisor: int) -> float:
        frac = {0: 0.0, 1: 0.5, 2: 0.25, 3: 0.125}[divisor >> 14]
        return 3e6 / ((divisor & 0x3FFF) + frac)

    assert rate(P.BAUD_DIVISOR_9600) == pytest.approx(9600)
    assert rate(P.BAUD_DIVISOR_FIRMWARE) == pytest.approx(142857, rel=1e-3)
    assert rate(P.BAUD_DIVISOR_NORMAL) == pytest.approx(1.5e6)


def test_split_packets_resyncs_and_keeps_a_partial_tail():
    good = P.encode_status((1, -2, 3), buttons=1, homed=(True, True, False))
    broken = b"<" + bytes(15)  # starts like a packet, does not decode
    buf = bytearray(b"xx" + good + broken + good + good[:5])
    items = list(P.split_packets(buf, P.decode_status))
    assert items[0] is None  # the garbage before the first '<'
    decoded = [i for i in items if i is not None]
    assert decoded == [P.decode_status(good)] * 2
    assert None in items[2:]  # the broken packet
    assert bytes(buf) == good[:5]  # waits for the rest
    buf += good[5:]
    assert list(P.split_packets(buf, P.decode_status)) == [P.decode_status(good)]
    assert buf == bytearray()
