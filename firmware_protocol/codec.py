"""Encode typed messages to CAN frames and back, with the layout of truck.dbc.

Physical values are scaled with the DBC's factors here (round to nearest, clamped to the
signal's raw range; non-finite values are refused) and packed as raw integers.  The bit
layout has exactly one definition, ``truck.dbc``: ``cantools`` loads it, and at load time
each message's signals (start bit, length, signedness, raw range) are compiled into a
:class:`Layout` that packs and unpacks with integer shifts and masks over the payload as
one little-endian integer (every signal of truck.dbc is Intel byte order; a Motorola
signal is refused at load).  This is what runs on the control loop (cantools' own
encode/decode cost about 30 us per frame there); tests prove it byte-identical with
cantools for every message.  Every message
ends with ``CHECKSUM`` (see :mod:`firmware_protocol.crc`) and carries a 4-bit
``COUNTER`` the caller supplies.

:func:`decode` raises only :class:`DecodeError` (unknown id, wrong length, bad checksum,
undecodable payload); it does not track counters or freshness (see
:mod:`firmware_protocol.checks`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import cantools

from firmware_protocol.crc import message_checksum
from firmware_protocol.messages import (
    SAMPLE_TIME_MODULO,
    TICKS_MODULO,
    CompanionHeartbeat,
    CompanionState,
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    Message,
    MotorCommand,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
)

DBC_PATH = Path(__file__).with_name("truck.dbc")


class DecodeError(ValueError):
    """A frame that is not a valid protocol message; ``reason`` is one of
    ``unknown_id``, ``length``, ``checksum``, ``payload``."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Frame:
    """One CAN frame: 11-bit id and payload bytes."""

    can_id: int
    data: bytes


@dataclass(frozen=True, slots=True)
class Decoded:
    """A decoded message with the counter it carried and its DBC name."""

    name: str
    msg: Message
    counter: int


class EncodeError(ValueError):
    """Raw values a message cannot carry (missing, unknown, or outside the DBC's range)."""


@dataclass(frozen=True, slots=True)
class Field:
    """One signal's place in the payload integer: bits ``start .. start+length-1``."""

    name: str
    start: int
    mask: int
    sign_bit: int
    """``1 << (length - 1)`` for a signed signal, 0 for an unsigned one."""
    lo: int
    hi: int
    """Raw range (the bit range narrowed by the DBC's physical limits)."""


def _bit_range(f: Field) -> tuple[int, int]:
    """The raw values the field's bits can hold."""
    if f.sign_bit:
        return -f.sign_bit, f.sign_bit - 1
    return 0, f.mask


class Layout:
    """Packs and unpacks one message's raw signal values (compiled from the DBC)."""

    __slots__ = ("checked", "checksum", "counter_mask", "fields", "length")

    def __init__(self, fields: tuple[Field, ...], length: int) -> None:
        self.fields = fields
        self.length = length
        self.checksum = next(f for f in fields if f.name == "CHECKSUM")
        self.counter_mask = next(f.mask for f in fields if f.name == "COUNTER")
        """COUNTER wraps at ``counter_mask + 1`` (its width in the DBC)."""
        self.checked = tuple(f for f in fields if (f.lo, f.hi) != _bit_range(f))
        """The fields whose raw range is narrower than their bits (the only ones a
        received value can fall outside of)."""

    def pack_int(self, raw: Mapping[str, int]) -> int:
        """The payload as an integer; every signal must be given, within its range."""
        if len(raw) != len(self.fields):
            names = {f.name for f in self.fields}
            raise EncodeError(f"signals {sorted(raw)} do not match the message's {sorted(names)}")
        x = 0
        try:
            for f in self.fields:
                v = raw[f.name]
                if not f.lo <= v <= f.hi:
                    raise EncodeError(f"{f.name}: raw {v} outside [{f.lo}, {f.hi}]")
                x |= (v & f.mask) << f.start
        except KeyError as exc:
            raise EncodeError(f"signal {exc} missing") from None
        return x

    def unpack(self, data: bytes) -> dict[str, int]:
        """Raw signal values of a payload of the message's length."""
        x = int.from_bytes(data, "little")
        out = {}
        for f in self.fields:
            v = (x >> f.start) & f.mask
            if v & f.sign_bit:
                v -= f.sign_bit << 1
            out[f.name] = v
        return out


@dataclass(frozen=True)
class MessageSpec:
    """What the codec knows about one DBC message."""

    name: str
    can_id: int
    length: int
    period: float
    """Nominal period, s (DBC ``GenMsgCycleTime``)."""
    scale: Mapping[str, float]
    raw_range: Mapping[str, tuple[int, int]]
    dbc: Any
    """The cantools message (the reference the fast :attr:`layout` is tested against)."""
    layout: Layout


@cache
def database() -> Any:
    """The loaded truck.dbc (cantools Database), cached."""
    return cantools.database.load_file(str(DBC_PATH), strict=True)


def _spec(m: Any) -> MessageSpec:
    scale: dict[str, float] = {}
    rng: dict[str, tuple[int, int]] = {}
    for s in m.signals:
        scale[s.name] = float(s.scale)
        if s.is_signed:
            lo, hi = -(1 << (s.length - 1)), (1 << (s.length - 1)) - 1
        else:
            lo, hi = 0, (1 << s.length) - 1
        # the DBC's physical limits, as raw values, narrow the bit range
        if s.minimum is not None:
            lo = max(lo, round((s.minimum - s.offset) / s.scale))
        if s.maximum is not None:
            hi = min(hi, round((s.maximum - s.offset) / s.scale))
        rng[s.name] = (lo, hi)
    fields = []
    for s in m.signals:
        if s.byte_order != "little_endian" or s.offset != 0 or s.is_float:
            raise ValueError(f"{m.name}.{s.name}: only Intel-order integer signals supported")
        fields.append(
            Field(
                name=s.name,
                start=s.start,
                mask=(1 << s.length) - 1,
                sign_bit=(1 << (s.length - 1)) if s.is_signed else 0,
                lo=rng[s.name][0],
                hi=rng[s.name][1],
            )
        )
    return MessageSpec(
        name=m.name,
        can_id=m.frame_id,
        length=m.length,
        period=(m.cycle_time or 0) / 1000.0,
        scale=scale,
        raw_range=rng,
        dbc=m,
        layout=Layout(tuple(fields), m.length),
    )


@cache
def specs() -> dict[str, MessageSpec]:
    """Every message of truck.dbc by name."""
    return {m.name: _spec(m) for m in database().messages}


@cache
def _by_id() -> dict[int, MessageSpec]:
    return {s.can_id: s for s in specs().values()}


def _raw(spec: MessageSpec, signal: str, value: float) -> int:
    if not math.isfinite(value):
        raise ValueError(f"{spec.name}.{signal}: value must be finite, got {value!r}")
    lo, hi = spec.raw_range[signal]
    r = value / spec.scale[signal]
    return lo if r <= lo else hi if r >= hi else round(r)


def _clamp_int(spec: MessageSpec, signal: str, value: int) -> int:
    lo, hi = spec.raw_range[signal]
    return lo if value < lo else hi if value > hi else int(value)


def _sample_raw(spec: MessageSpec, t: float) -> int:
    if not math.isfinite(t):
        raise ValueError(f"{spec.name}.SAMPLE_TIME must be finite, got {t!r}")
    return round((t % SAMPLE_TIME_MODULO) / spec.scale["SAMPLE_TIME"]) % TICKS_MODULO


def _signals(msg: Message) -> tuple[str, dict[str, int]]:
    """DBC message name and raw signal values (without COUNTER/CHECKSUM)."""
    if isinstance(msg, MotorCommand):
        s = specs()["MOTOR_CMD"]
        return s.name, {"VOLTAGE": _raw(s, "VOLTAGE", msg.voltage), "ENABLE": int(msg.enable)}
    if isinstance(msg, CompanionHeartbeat):
        s = specs()["COMPANION_HEARTBEAT"]
        return s.name, {
            "STATE": _clamp_int(s, "STATE", int(msg.state)),
            "FAULTS": _clamp_int(s, "FAULTS", int(msg.faults)),
        }
    if isinstance(msg, WheelEncoders):
        s = specs()["WHEEL_ENCODERS"]
        return s.name, {
            "TICKS_LEFT": int(msg.ticks_left) % TICKS_MODULO,
            "TICKS_RIGHT": int(msg.ticks_right) % TICKS_MODULO,
            "SAMPLE_TIME": _sample_raw(s, msg.sample_time),
            "STATUS": _clamp_int(s, "STATUS", int(msg.status)),
        }
    if isinstance(msg, MotorFeedback):
        s = specs()["MOTOR_FEEDBACK"]
        return s.name, {
            "CURRENT": _raw(s, "CURRENT", msg.current),
            "VBAT": _raw(s, "VBAT", msg.vbat),
            "U_APPLIED": _raw(s, "U_APPLIED", msg.u_applied),
            "STATUS": _clamp_int(s, "STATUS", int(msg.status)),
        }
    if isinstance(msg, RangeReading):
        s = specs()["RANGE"]
        return s.name, {
            "DISTANCE": _raw(s, "DISTANCE", msg.distance),
            "SAMPLE_TIME": _sample_raw(s, msg.sample_time),
            "STATUS": _clamp_int(s, "STATUS", int(msg.status)),
        }
    if isinstance(msg, FirmwareHeartbeat):
        s = specs()["FIRMWARE_HEARTBEAT"]
        return s.name, {
            "STATE": _clamp_int(s, "STATE", int(msg.state)),
            "FAULTS": _clamp_int(s, "FAULTS", int(msg.faults)),
            "CMD_ERRORS": int(msg.cmd_errors) % 256,
        }
    raise TypeError(f"not a protocol message: {type(msg).__name__}")


def encode_raw(name: str, raw: Mapping[str, int], counter: int) -> Frame:
    """Pack raw signal values (COUNTER given, CHECKSUM computed).

    Raises :class:`EncodeError` for a missing or unknown signal or a raw value outside the
    DBC's range (as cantools' strict encoding does)."""
    values = dict(raw)
    spec = specs()[name]
    values["COUNTER"] = counter & spec.layout.counter_mask
    values["CHECKSUM"] = 0
    return _pack(spec, values)


def _pack(spec: MessageSpec, values: Mapping[str, int]) -> Frame:
    """The frame of every raw value, COUNTER given and CHECKSUM 0 (computed here)."""
    lay = spec.layout
    x = lay.pack_int(values)
    n = lay.length
    cs = message_checksum(spec.can_id, x.to_bytes(n, "little")[:-1])
    x |= cs << lay.checksum.start
    return Frame(spec.can_id, x.to_bytes(n, "little"))


def encode(msg: Message, counter: int) -> Frame:
    """The frame of a typed message with COUNTER = ``counter`` modulo its range (16).

    Values are rounded to the signal resolution and clamped to its range; a non-finite
    value raises ValueError (nothing is sent).
    """
    name, raw = _signals(msg)  # a new dict: completed in place
    spec = specs()[name]
    raw["COUNTER"] = counter & spec.layout.counter_mask
    raw["CHECKSUM"] = 0
    return _pack(spec, raw)


def decode_raw(frame: Frame) -> tuple[MessageSpec, dict[str, int]]:
    """Check id, length and checksum; return the raw signal values.

    Raises :class:`DecodeError` only.
    """
    spec = _by_id().get(frame.can_id)
    if spec is None:
        raise DecodeError("unknown_id", f"id 0x{frame.can_id:X}")
    data = frame.data
    if len(data) != spec.length:
        raise DecodeError("length", f"{spec.name}: {len(data)} bytes, expected {spec.length}")
    if message_checksum(spec.can_id, data[:-1]) != data[-1]:
        raise DecodeError("checksum", f"{spec.name}: CRC-8 mismatch")
    values = spec.layout.unpack(data)
    for f in spec.layout.checked:
        v = values[f.name]
        if not f.lo <= v <= f.hi:
            raise DecodeError("payload", f"{spec.name}.{f.name}: raw {v} outside [{f.lo}, {f.hi}]")
    return spec, values


def _enum(cls: Callable[[int], Any], value: int, name: str) -> Any:
    try:
        return cls(value)
    except ValueError:
        raise DecodeError("payload", f"{name}: value {value} not defined") from None


def _motor_cmd(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return MotorCommand(voltage=r["VOLTAGE"] * sc["VOLTAGE"], enable=bool(r["ENABLE"]))


def _companion_heartbeat(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return CompanionHeartbeat(
        state=_enum(CompanionState, r["STATE"], "COMPANION_HEARTBEAT.STATE"),
        faults=r["FAULTS"],
    )


def _wheel_encoders(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return WheelEncoders(
        ticks_left=r["TICKS_LEFT"],
        ticks_right=r["TICKS_RIGHT"],
        sample_time=r["SAMPLE_TIME"] * sc["SAMPLE_TIME"],
        status=r["STATUS"],
    )


def _motor_feedback(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return MotorFeedback(
        current=r["CURRENT"] * sc["CURRENT"],
        vbat=r["VBAT"] * sc["VBAT"],
        u_applied=r["U_APPLIED"] * sc["U_APPLIED"],
        status=r["STATUS"],
    )


def _range(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return RangeReading(
        distance=r["DISTANCE"] * sc["DISTANCE"],
        status=_enum(RangeStatus, r["STATUS"], "RANGE.STATUS"),
        sample_time=r["SAMPLE_TIME"] * sc["SAMPLE_TIME"],
    )


def _firmware_heartbeat(sc: Mapping[str, float], r: Mapping[str, int]) -> Message:
    return FirmwareHeartbeat(
        state=_enum(FirmwareState, r["STATE"], "FIRMWARE_HEARTBEAT.STATE"),
        faults=FirmwareFault(r["FAULTS"]),
        cmd_errors=r["CMD_ERRORS"],
    )


_BUILDERS: dict[str, Callable[[Mapping[str, float], Mapping[str, int]], Message]] = {
    "MOTOR_CMD": _motor_cmd,
    "COMPANION_HEARTBEAT": _companion_heartbeat,
    "WHEEL_ENCODERS": _wheel_encoders,
    "MOTOR_FEEDBACK": _motor_feedback,
    "RANGE": _range,
    "FIRMWARE_HEARTBEAT": _firmware_heartbeat,
}
"""The typed message of each DBC message, from its scales and raw values."""


def _build(spec: MessageSpec, r: Mapping[str, int]) -> Message:
    build = _BUILDERS.get(spec.name)
    if build is None:  # pragma: no cover
        raise DecodeError("unknown_id", f"no typed message for {spec.name}")
    return build(spec.scale, r)


def decode(frame: Frame) -> Decoded:
    """The typed message in a frame.  Raises :class:`DecodeError` only."""
    spec, raw = decode_raw(frame)
    return Decoded(spec.name, _build(spec, raw), raw["COUNTER"])


def message_name(msg: Message) -> str:
    """The DBC name of a typed message."""
    return _NAMES[type(msg)]


_NAMES: dict[type, str] = {
    MotorCommand: "MOTOR_CMD",
    CompanionHeartbeat: "COMPANION_HEARTBEAT",
    WheelEncoders: "WHEEL_ENCODERS",
    MotorFeedback: "MOTOR_FEEDBACK",
    RangeReading: "RANGE",
    FirmwareHeartbeat: "FIRMWARE_HEARTBEAT",
}
