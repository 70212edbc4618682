"""Serial framing: COBS, CRC-16, exact wire bytes, resynchronisation after garbage."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.codec import Frame, encode
from firmware_protocol.framing import (
    MAX_BODY,
    Deframer,
    FramingError,
    body_to_frame,
    cobs_decode,
    cobs_encode,
    frame_to_bytes,
)
from firmware_protocol.messages import MotorCommand


def test_cobs_known_vectors() -> None:
    # examples from the COBS paper / Wikipedia
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    block = bytes(range(1, 255))  # 254 non-zero bytes
    assert cobs_encode(block) == b"\xff" + block + b"\x01"


@given(st.binary(max_size=600))
def test_cobs_round_trip_and_no_zero(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    assert cobs_decode(enc) == data
    assert len(enc) <= len(data) + len(data) // 254 + 1


def test_exact_wire_bytes() -> None:
    frame = encode(MotorCommand(1.5, True), 1)
    # raw = 00 01 | dc 05 11 8e | CRC-16 LE; COBS turns the leading 0x00 into code 0x01
    wire = frame_to_bytes(frame)
    assert wire == bytes.fromhex("00010801dc05118e84e800")


@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_frame_round_trip(can_id: int, data: bytes) -> None:
    wire = frame_to_bytes(Frame(can_id, data))
    assert wire[0] == 0 and wire[-1] == 0 and 0 not in wire[1:-1]
    assert body_to_frame(wire[1:-1]) == Frame(can_id, data)
    assert Deframer().feed(wire) == [Frame(can_id, data)]


def test_frame_limits() -> None:
    with pytest.raises(ValueError):
        frame_to_bytes(Frame(0x800, b""))
    with pytest.raises(ValueError):
        frame_to_bytes(Frame(1, bytes(9)))
    with pytest.raises(FramingError):
        body_to_frame(b"\x02\x01")  # decodes to 1 byte: too short


frames_st = st.lists(
    st.builds(Frame, st.integers(0, 0x7FF), st.binary(max_size=8)), min_size=1, max_size=12
)


@settings(max_examples=300)
@given(frames_st, st.lists(st.binary(max_size=64), min_size=1, max_size=12), st.data())
def test_no_intact_frame_lost_after_garbage(
    frames: list[Frame], bursts: list[bytes], data: st.DataObject
) -> None:
    """Garbage between frames never costs an intact frame; every garbage run is counted."""
    stream = bytearray()
    for k, f in enumerate(frames):
        stream += bursts[k % len(bursts)]
        stream += frame_to_bytes(f)
    # feed in arbitrary chunks
    d = Deframer()
    got: list[Frame] = []
    pos = 0
    while pos < len(stream):
        n = data.draw(st.integers(1, 40))
        got += d.feed(bytes(stream[pos : pos + n]))
        pos += n
    # a garbage run can (rarely) pass COBS + CRC-16 as a frame; it is extra, never a loss
    it = iter(got)
    assert all(any(g == f for g in it) for f in frames)
    assert d.stats.frames_ok == len(got)


def test_garbage_statistics() -> None:
    d = Deframer()
    f = encode(MotorCommand(1.0, True), 0)
    garbage = bytes([0x55] * 40)  # longer than any body: overflow, discarded as it arrives
    out = d.feed(garbage + frame_to_bytes(f) + b"\x12\x34" + frame_to_bytes(f))
    assert out == [f, f]
    assert d.stats.resyncs == 2
    assert d.stats.bytes_discarded == 42
    assert d.stats.length_errors == 1  # the overflow
    assert d.stats.crc_errors + d.stats.cobs_errors == 1  # the 2-byte run


def test_corrupted_frame_counted_not_passed() -> None:
    wire = bytearray(frame_to_bytes(Frame(0x210, bytes(range(1, 9)))))
    wire[5] ^= 0x40
    d = Deframer()
    assert d.feed(bytes(wire)) == []
    assert d.stats.crc_errors + d.stats.cobs_errors + d.stats.length_errors == 1


def test_overflow_bounded_memory() -> None:
    d = Deframer()
    d.feed(b"\x07" * 10_000)
    assert len(d._buf) <= MAX_BODY
    assert d.feed(frame_to_bytes(Frame(1, b"\x01"))) == [Frame(1, b"\x01")]
