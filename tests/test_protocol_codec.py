"""The DBC and the codec: exact bytes, round trips, limits, errors."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys

import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_protocol.codec import (
    DBC_PATH,
    DecodeError,
    Frame,
    decode,
    encode,
    message_name,
    specs,
)
from firmware_protocol.crc import crc8_j1850, crc16_ccitt, crc16_ccitt_table
from firmware_protocol.messages import (
    CompanionHeartbeat,
    CompanionState,
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    MotorCommand,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
    sample_time_delta,
    ticks_delta,
)


def crc8_bitwise(data: bytes) -> int:
    """Reference CRC-8/SAE-J1850, bit by bit (independent of the table code)."""
    crc = 0xFF
    for b in data:
        for i in range(7, -1, -1):
            bit = ((b >> i) & 1) ^ (crc >> 7)
            crc = ((crc << 1) & 0xFF) ^ (0x1D if bit else 0)
    return crc ^ 0xFF


def test_crc_catalogue_check_values() -> None:
    # reveng catalogue "check" values for the input "123456789"
    assert crc8_j1850(b"123456789") == 0x4B
    assert crc16_ccitt(b"123456789") == 0x29B1


@given(st.binary(max_size=40))
def test_crc16_matches_the_python_table(data: bytes) -> None:
    assert crc16_ccitt(data) == crc16_ccitt_table(data)


@given(st.binary(max_size=20))
def test_crc8_table_matches_bitwise(data: bytes) -> None:
    assert crc8_j1850(data) == crc8_bitwise(data)


# (message, counter, id, payload): layouts checked by hand against truck.dbc, e.g.
# MOTOR_CMD -2.0 V = raw -2000 = 0xF830 LE "30 f8", byte 2 = ENABLE 0 | COUNTER 15 << 4.
VECTORS = [
    (MotorCommand(1.5, True), 1, 0x100, "dc0511"),
    (MotorCommand(-2.0, False), 15, 0x100, "30f8f0"),
    (CompanionHeartbeat(CompanionState.DEGRADED, 0x0102), 3, 0x110, "320201"),
    (WheelEncoders(0x1234, 0xABCD, 1.0, 2), 5, 0x200, "3412cdab102752"),
    (MotorFeedback(-2.5, 7.2, 3.3, 1), 7, 0x210, "06ff201ce40c71"),
    (RangeReading(1.234, RangeStatus.VALID, 0.5), 9, 0x220, "d20488139066"[:10]),
    (RangeReading(0.0, RangeStatus.NO_TARGET, 0.0), 0, 0x220, "0000000001"),
    (
        FirmwareHeartbeat(
            FirmwareState.FAILSAFE, FirmwareFault.CMD_TIMEOUT | FirmwareFault.COMPANION_TIMEOUT, 44
        ),
        2,
        0x300,
        "2381002c",
    ),
]


@pytest.mark.parametrize(("msg", "counter", "can_id", "body"), VECTORS)
def test_exact_bytes(msg: object, counter: int, can_id: int, body: str) -> None:
    frame = encode(msg, counter)  # type: ignore[arg-type]
    head = bytes.fromhex(body)
    checksum = crc8_bitwise(bytes((can_id & 0xFF, can_id >> 8)) + head)
    assert frame == Frame(can_id, head + bytes((checksum,)))
    dec = decode(frame)
    assert dec.counter == counter
    assert dec.name == message_name(msg)  # type: ignore[arg-type]


def test_exact_checksums() -> None:
    # spot values, so a change of CRC parameters cannot pass unnoticed
    assert encode(MotorCommand(1.5, True), 1).data == bytes.fromhex("dc05118e")
    assert encode(FirmwareHeartbeat(FirmwareState.IDLE, FirmwareFault.NONE, 0), 0).data[-1] == (
        crc8_bitwise(bytes.fromhex("0003" + "01000000"))
    )


def test_dbc_periods_and_layout() -> None:
    s = specs()
    assert {n: s[n].period for n in s} == {
        "MOTOR_CMD": 0.01,
        "COMPANION_HEARTBEAT": 0.1,
        "WHEEL_ENCODERS": 0.01,
        "MOTOR_FEEDBACK": 0.01,
        "RANGE": 0.02,
        "FIRMWARE_HEARTBEAT": 0.1,
    }
    for sp in s.values():
        sigs = {sig.name: sig for sig in sp.dbc.signals}
        assert sigs["COUNTER"].length == 4
        assert sigs["CHECKSUM"].length == 8
        assert sigs["CHECKSUM"].start == 8 * sp.length - 8  # always the last byte


def test_cantools_dump_reads_the_dbc() -> None:
    exe = shutil.which("cantools", path=str(__import__("pathlib").Path(sys.executable).parent))
    cmd = [exe] if exe else [sys.executable, "-m", "cantools"]
    out = subprocess.run(
        [*cmd, "dump", str(DBC_PATH)], capture_output=True, text=True, timeout=60, check=True
    ).stdout
    for name in specs():
        assert f"Name:           {name}" in out
    assert "Cycle time:     10 ms" in out


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def _close(a: float, b: float, res: float) -> bool:
    return abs(a - b) <= res / 2 + 1e-9


@given(st.floats(-32.767, 32.767), st.booleans(), st.integers(0, 15))
def test_motor_command_round_trip(v: float, en: bool, c: int) -> None:
    d = decode(encode(MotorCommand(v, en), c))
    assert isinstance(d.msg, MotorCommand)
    assert _close(d.msg.voltage, v, 0.001) and d.msg.enable == en and d.counter == c


@given(st.sampled_from(CompanionState), st.integers(0, 0xFFFF), st.integers(0, 15))
def test_companion_heartbeat_round_trip(s: CompanionState, f: int, c: int) -> None:
    d = decode(encode(CompanionHeartbeat(s, f), c))
    assert d.msg == CompanionHeartbeat(s, f) and d.counter == c


@given(
    st.integers(-(10**9), 10**9),
    st.integers(-(10**9), 10**9),
    st.floats(0, 1e5),
    st.integers(0, 15),
    st.integers(0, 15),
)
def test_wheel_encoders_round_trip(tl: int, tr: int, t: float, status: int, c: int) -> None:
    d = decode(encode(WheelEncoders(tl, tr, t, status), c))
    m = d.msg
    assert isinstance(m, WheelEncoders)
    assert m.ticks_left == tl % 65536 and m.ticks_right == tr % 65536 and m.status == status
    err = abs(sample_time_delta(m.sample_time, t))
    assert min(err, 6.5536 - err) <= 0.00005 + 1e-9


@given(
    st.floats(-327.68, 327.67), st.floats(0, 65.535), st.floats(-32.768, 32.767), st.integers(0, 15)
)
def test_motor_feedback_round_trip(i: float, vb: float, u: float, s: int) -> None:
    m = decode(encode(MotorFeedback(i, vb, u, s), 4)).msg
    assert isinstance(m, MotorFeedback)
    assert _close(m.current, i, 0.01) and _close(m.vbat, vb, 0.001)
    assert _close(m.u_applied, u, 0.001) and m.status == s


@given(st.floats(0, 65.535), st.sampled_from(RangeStatus), st.floats(0, 6.55))
def test_range_round_trip(dist: float, s: RangeStatus, t: float) -> None:
    m = decode(encode(RangeReading(dist, s, t), 11)).msg
    assert isinstance(m, RangeReading)
    assert _close(m.distance, dist, 0.001) and m.status == s and _close(m.sample_time, t, 1e-4)
    assert (m.gap is not None) == (s == RangeStatus.VALID) == m.valid


@given(st.sampled_from(FirmwareState), st.integers(0, 0xFFFF), st.integers(0, 10**6))
def test_firmware_heartbeat_round_trip(s: FirmwareState, f: int, e: int) -> None:
    m = decode(encode(FirmwareHeartbeat(s, FirmwareFault(f), e), 0)).msg
    assert m == FirmwareHeartbeat(s, FirmwareFault(f), e % 256)


@given(finite)
def test_out_of_range_values_saturate(v: float) -> None:
    m = decode(encode(MotorCommand(v, True), 0)).msg
    assert isinstance(m, MotorCommand)
    assert -32.767 <= m.voltage <= 32.767
    if abs(v) >= 32.767:
        assert m.voltage == math.copysign(32.767, v)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="finite"):
        encode(MotorCommand(bad, True), 0)
    with pytest.raises(ValueError, match="finite"):
        encode(RangeReading(bad, RangeStatus.VALID), 0)


def test_decode_errors_name_the_reason() -> None:
    good = encode(MotorCommand(1.0, True), 0)
    cases = {
        "unknown_id": Frame(0x7FF, good.data),
        "length": Frame(good.can_id, good.data + b"\x00"),
        "checksum": Frame(good.can_id, good.data[:-1] + bytes((good.data[-1] ^ 1,))),
    }
    for reason, frame in cases.items():
        with pytest.raises(DecodeError) as ei:
            decode(frame)
        assert ei.value.reason == reason


def test_undefined_enum_and_out_of_range_raw_are_payload_errors() -> None:
    from firmware_protocol.codec import encode_raw

    bad_state = encode_raw("FIRMWARE_HEARTBEAT", {"STATE": 9, "FAULTS": 0, "CMD_ERRORS": 0}, 0)
    with pytest.raises(DecodeError) as ei:
        decode(bad_state)
    assert ei.value.reason == "payload"
    # raw -32768 is a valid int16 but below the DBC minimum -32.767 V
    data = bytes((0x00, 0x80, 0x01))
    from firmware_protocol.crc import message_checksum

    frame = Frame(0x100, data + bytes((message_checksum(0x100, data),)))
    with pytest.raises(DecodeError) as ei:
        decode(frame)
    assert ei.value.reason == "payload"


def test_wrap_helpers() -> None:
    assert ticks_delta(5, 65530) == 11
    assert ticks_delta(65530, 5) == -11
    assert ticks_delta(100, 100) == 0
    assert math.isclose(sample_time_delta(0.001, 6.5535), 0.0011, abs_tol=1e-12)
