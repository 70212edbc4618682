"""The compiled pack/unpack (the control loop's codec) against cantools on truck.dbc:
byte-identical frames and identical raw values for every message over drawn values."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from firmware_protocol.codec import EncodeError, Frame, decode_raw, encode_raw, specs
from firmware_protocol.crc import message_checksum

NAMES = sorted(specs())


def _bit_range(sig: Any) -> tuple[int, int]:
    if sig.is_signed:
        return -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    return 0, (1 << sig.length) - 1


def cantools_encode_raw(name: str, raw: dict[str, int], counter: int) -> bytes:
    """The reference: cantools' strict encoding, checksum over the payload with it 0."""
    m = specs()[name].dbc
    values = dict(raw)
    values["COUNTER"] = counter & 0xF
    values["CHECKSUM"] = 0
    data = m.encode(values, scaling=False, strict=True)
    values["CHECKSUM"] = message_checksum(m.frame_id, data[:-1])
    return bytes(m.encode(values, scaling=False, strict=False))


@st.composite
def raw_values(draw: st.DrawFn, name: str, within: bool) -> dict[str, int]:
    """Raw values of a message's signals (without COUNTER/CHECKSUM): within the DBC's range,
    or anywhere in the signal's bit range (may be outside the physical limits)."""
    sp = specs()[name]
    out = {}
    for sig in sp.dbc.signals:
        if sig.name in ("COUNTER", "CHECKSUM"):
            continue
        lo, hi = sp.raw_range[sig.name] if within else _bit_range(sig)
        out[sig.name] = draw(st.integers(lo, hi))
    return out


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=150, deadline=None)
@given(data=st.data(), counter=st.integers(0, 255))
def test_encode_is_byte_identical_with_cantools(
    name: str, data: st.DataObject, counter: int
) -> None:
    raw = data.draw(raw_values(name, within=True))
    frame = encode_raw(name, raw, counter)
    assert frame.data == cantools_encode_raw(name, raw, counter)
    assert frame.can_id == specs()[name].can_id


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=150, deadline=None)
@given(data=st.data(), counter=st.integers(0, 15))
def test_out_of_range_raw_is_refused_like_cantools(
    name: str, data: st.DataObject, counter: int
) -> None:
    raw = data.draw(raw_values(name, within=False))
    try:
        expected: bytes | None = cantools_encode_raw(name, raw, counter)
    except Exception:  # cantools' EncodeError
        expected = None
    if expected is None:
        with pytest.raises(EncodeError):
            encode_raw(name, raw, counter)
    else:
        assert encode_raw(name, raw, counter).data == expected


@pytest.mark.parametrize("name", NAMES)
def test_missing_or_unknown_signals_are_refused(name: str) -> None:
    sp = specs()[name]
    raw = {k: lo for k, (lo, _) in sp.raw_range.items() if k not in ("COUNTER", "CHECKSUM")}
    first = next(iter(raw))
    with pytest.raises(EncodeError):
        encode_raw(name, {k: v for k, v in raw.items() if k != first}, 0)
    with pytest.raises(EncodeError):
        encode_raw(name, {**raw, "NOT_A_SIGNAL": 0}, 0)


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_unpack_equals_cantools_decode_on_any_payload(name: str, data: st.DataObject) -> None:
    """Any payload bytes (valid checksum appended): the same raw values as cantools, and a
    payload error exactly when one is outside the DBC's range."""
    sp = specs()[name]
    body = data.draw(st.binary(min_size=sp.length - 1, max_size=sp.length - 1))
    payload = body + bytes((message_checksum(sp.can_id, body),))
    ref = {
        k: int(v) for k, v in sp.dbc.decode(payload, decode_choices=False, scaling=False).items()
    }
    assert sp.layout.unpack(payload) == ref
    in_range = all(sp.raw_range[k][0] <= v <= sp.raw_range[k][1] for k, v in ref.items())
    if in_range:
        assert decode_raw(Frame(sp.can_id, payload))[1] == ref
    else:
        with pytest.raises(ValueError):
            decode_raw(Frame(sp.can_id, payload))
