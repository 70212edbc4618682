"""The protocol's timing, read from truck.dbc: periods, the command timeout, counter limits;
and the microcontroller's default limits (undervoltage, the range sensor's valid span).

One definition for Python and C: :mod:`firmware_protocol.generate` writes the same numbers
into ``c/truck_timing.h`` for the firmware (and cantools' ``truck.h`` carries the periods
as ``TRUCK_<MESSAGE>_CYCLE_TIME_MS``).  Where they come from in the DBC:

- a message's period: ``GenMsgCycleTime`` (ms);
- a message's hard receive timeout: ``TruckTimeoutTime`` (ms; MOTOR_CMD: the
  microcontroller switches the motor off after this long without a valid command);
- the counter width: the ``COUNTER`` signal's length (the same in every message);
- ``TruckCounterMaxDelta``, ``TruckCounterResync``, ``TruckCounterMaxWrong``: the counter
  rules of :mod:`firmware_protocol.checks`; ``TruckFreshnessPeriods``: a received message
  is stale after this many of its periods (the microcontroller's default);
- ``TruckUndervoltageMv``, ``TruckRangeMinMm``, ``TruckRangeMaxMm``: the microcontroller's
  default limits (:class:`FirmwareLimits`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

from firmware_protocol.codec import DBC_PATH, database


@dataclass(frozen=True)
class ProtocolTiming:
    """The timing numbers of truck.dbc (SI: seconds)."""

    periods: Mapping[str, float]
    """Each message's period (``GenMsgCycleTime``), s."""
    timeouts: Mapping[str, float]
    """The messages with a hard receive timeout (``TruckTimeoutTime``), s."""
    counter_bits: int
    counter_max_delta: int
    counter_resync: int
    counter_max_wrong: int
    freshness_periods: int

    @property
    def counter_modulo(self) -> int:
        """COUNTER counts 0 .. modulo - 1."""
        return 1 << self.counter_bits

    @property
    def cmd_timeout(self) -> float:
        """The microcontroller's command timeout (s): motor off after this long without a
        valid MOTOR_CMD."""
        return self.timeouts["MOTOR_CMD"]

    @property
    def heartbeat_period(self) -> float:
        """The companion heartbeat's period (s)."""
        return self.periods["COMPANION_HEARTBEAT"]


@dataclass(frozen=True)
class FirmwareLimits:
    """The microcontroller's default limits in truck.dbc (SI)."""

    undervoltage: float
    """V: FAULTS bit UNDERVOLTAGE below this battery voltage (``TruckUndervoltageMv``)."""
    range_min: float
    """m: a range reading below this is sent as this (``TruckRangeMinMm``)."""
    range_max: float
    """m: a range reading beyond this is NO_TARGET (``TruckRangeMaxMm``)."""


def _network_int(db: Any, name: str) -> int:
    attrs = db.dbc.attributes
    if name in attrs:
        return int(attrs[name].value)
    definition = db.dbc.attribute_definitions.get(name)
    if definition is None or definition.default_value is None:
        raise ValueError(f"{DBC_PATH.name}: attribute {name} is not defined")
    return int(definition.default_value)


@cache
def timing() -> ProtocolTiming:
    """The timing of truck.dbc (loaded once)."""
    return timing_of(database())


def timing_of(db: Any) -> ProtocolTiming:
    """The timing of a loaded DBC (a cantools Database)."""
    periods: dict[str, float] = {}
    timeouts: dict[str, float] = {}
    widths: set[int] = set()
    for m in db.messages:
        periods[m.name] = (m.cycle_time or 0) / 1000.0
        attr = m.dbc.attributes.get("TruckTimeoutTime") if m.dbc is not None else None
        if attr is not None and int(attr.value) > 0:
            timeouts[m.name] = int(attr.value) / 1000.0
        widths |= {s.length for s in m.signals if s.name == "COUNTER"}
    if len(widths) != 1:
        raise ValueError(f"{DBC_PATH.name}: COUNTER widths differ between messages: {widths}")
    if "MOTOR_CMD" not in timeouts:
        raise ValueError(f"{DBC_PATH.name}: MOTOR_CMD has no TruckTimeoutTime")
    return ProtocolTiming(
        periods=periods,
        timeouts=timeouts,
        counter_bits=widths.pop(),
        counter_max_delta=_network_int(db, "TruckCounterMaxDelta"),
        counter_resync=_network_int(db, "TruckCounterResync"),
        counter_max_wrong=_network_int(db, "TruckCounterMaxWrong"),
        freshness_periods=_network_int(db, "TruckFreshnessPeriods"),
    )


@cache
def limits() -> FirmwareLimits:
    """The microcontroller's default limits in truck.dbc (loaded once)."""
    return limits_of(database())


def limits_of(db: Any) -> FirmwareLimits:
    """The microcontroller's default limits of a loaded DBC (a cantools Database)."""
    lo, hi = _network_int(db, "TruckRangeMinMm"), _network_int(db, "TruckRangeMaxMm")
    if not lo < hi:
        raise ValueError(f"{DBC_PATH.name}: TruckRangeMinMm {lo} is not below TruckRangeMaxMm {hi}")
    return FirmwareLimits(
        undervoltage=_network_int(db, "TruckUndervoltageMv") / 1000.0,
        range_min=lo / 1000.0,
        range_max=hi / 1000.0,
    )


def c_header(t: ProtocolTiming | None = None, lim: FirmwareLimits | None = None) -> str:
    """``c/truck_timing.h``: the same numbers for the firmware (truck.dbc's by default)."""
    t = t if t is not None else timing()
    lim = lim if lim is not None else limits()
    ms = {name: round(s * 1000.0) for name, s in t.timeouts.items()}
    lines = [
        "/**",
        " * truck_timing.h: protocol timing and the microcontroller's default limits from",
        f" * {DBC_PATH.name}, generated by python -m firmware_protocol.generate",
        " * (firmware_protocol/timing.py): do not edit.",
        " * Message periods are in truck.h (TRUCK_<MESSAGE>_CYCLE_TIME_MS).",
        " */",
        "#ifndef TRUCK_TIMING_H",
        "#define TRUCK_TIMING_H",
        "",
        "/** COUNTER width (bits), modulo and mask. */",
        f"#define TRUCK_COUNTER_BITS ({t.counter_bits}u)",
        f"#define TRUCK_COUNTER_MODULO ({t.counter_modulo}u)",
        f"#define TRUCK_COUNTER_MASK ({t.counter_modulo - 1}u)",
        "/** The largest forward counter jump taken as lost frames (TruckCounterMaxDelta). */",
        f"#define TRUCK_COUNTER_MAX_DELTA ({t.counter_max_delta}u)",
        "/** In-sequence frames needed after a larger jump (TruckCounterResync). */",
        f"#define TRUCK_COUNTER_RESYNC ({t.counter_resync}u)",
        "/** Counter score limit (TruckCounterMaxWrong). */",
        f"#define TRUCK_COUNTER_MAX_WRONG ({t.counter_max_wrong}u)",
        "/** A received message is stale after this many periods (TruckFreshnessPeriods). */",
        f"#define TRUCK_FRESHNESS_PERIODS ({t.freshness_periods}u)",
        "",
        "/** Hard receive timeouts (TruckTimeoutTime), ms. */",
        *(f"#define TRUCK_{name}_TIMEOUT_MS ({v}u)" for name, v in sorted(ms.items())),
        "",
        "/** The microcontroller's default limits: UNDERVOLTAGE below this battery voltage",
        " * (TruckUndervoltageMv, mV); range readings below the minimum are sent as it, beyond",
        " * the maximum as NO_TARGET (TruckRangeMinMm, TruckRangeMaxMm, mm). */",
        f"#define TRUCK_UNDERVOLTAGE_MV ({round(lim.undervoltage * 1000.0)})",
        f"#define TRUCK_RANGE_MIN_MM ({round(lim.range_min * 1000.0)})",
        f"#define TRUCK_RANGE_MAX_MM ({round(lim.range_max * 1000.0)})",
        "",
        "#endif",
        "",
    ]
    return "\n".join(lines)
