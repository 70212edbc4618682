"""Bus and line load arithmetic against hand-computed values."""

from __future__ import annotations

import pytest

from firmware_protocol.busload import can_bus_load, can_frame_bits, serial_frame_bytes, serial_load


def test_can_frame_bits() -> None:
    # 8-byte standard frame: 111 bits incl. IFS, +24 stuff bits worst case (CiA figures)
    assert can_frame_bits(8, worst_case_stuffing=False) == 111
    assert can_frame_bits(8) == 135
    assert can_frame_bits(0) == 47 + 8


def test_protocol_load() -> None:
    # 100 Hz x (4-byte cmd 95 + two 8-byte 135) + 50 Hz x 6-byte 115 + 10 Hz x (95 + 105)
    bits = 100 * (95 + 135 + 135) + 50 * 115 + 10 * (95 + 105)
    assert can_bus_load(500_000) == pytest.approx(bits / 500_000)
    assert can_bus_load(500_000) < 0.10
    assert serial_frame_bytes(8) == 15
    up, down = serial_load(115_200)
    assert up == pytest.approx((100 * 15 * 2 + 50 * 13 + 10 * 12) * 10 / 115_200)
    assert down == pytest.approx((100 * 11 + 10 * 11) * 10 / 115_200)
