"""Typed messages of the firmware protocol, in SI units (no bytes here).

Messages the companion computer sends: :class:`MotorCommand` (10 ms),
:class:`CompanionHeartbeat` (100 ms).  Messages the microcontroller sends:
:class:`WheelEncoders` (10 ms), :class:`MotorFeedback` (10 ms), :class:`RangeReading`
(20 ms), :class:`FirmwareHeartbeat` (100 ms).  ``COUNTER`` and ``CHECKSUM`` live in the
codec, not here.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag

TICKS_MODULO = 1 << 16
"""Encoder counts wrap at 2^16."""

SAMPLE_TIME_MODULO = 6.5536
"""Sample times (s, the MCU clock) wrap at 2^16 * 100 us."""


class CompanionState(IntEnum):
    """Supervisor mode the companion computer reports in its heartbeat."""

    INIT = 0
    ACTIVE = 1
    DEGRADED = 2
    SAFE_STOP = 3
    FAULT = 4


class FirmwareState(IntEnum):
    """Microcontroller state: IDLE = no valid command yet or disabled; FAILSAFE = motor
    forced off (command timeout)."""

    BOOT = 0
    IDLE = 1
    ACTIVE = 2
    FAILSAFE = 3


class FirmwareFault(IntFlag):
    """Fault bits of the microcontroller heartbeat."""

    NONE = 0
    CMD_TIMEOUT = 1 << 0
    CMD_CHECKSUM = 1 << 1
    CMD_COUNTER = 1 << 2
    RANGE_SENSOR = 1 << 3
    ENCODER = 1 << 4
    UNDERVOLTAGE = 1 << 5
    CMD_INVALID = 1 << 6
    COMPANION_TIMEOUT = 1 << 7


class RangeStatus(IntEnum):
    """Validity of a range reading."""

    VALID = 0
    NO_TARGET = 1
    SENSOR_FAULT = 2


@dataclass(frozen=True, slots=True)
class MotorCommand:
    """Armature voltage command (V, clamped by the MCU to the battery) and enable."""

    voltage: float
    enable: bool


@dataclass(frozen=True, slots=True)
class CompanionHeartbeat:
    """Companion supervisor state and its fault bits (16 bits, meaning owned by truckd)."""

    state: CompanionState
    faults: int = 0


@dataclass(frozen=True, slots=True)
class WheelEncoders:
    """Encoder counts of both driven wheels (wrapping at 2^16) and the MCU sample time
    (s, wrapping at 6.5536 s).  ``status`` bit 0/1: left/right encoder fault."""

    ticks_left: int
    ticks_right: int
    sample_time: float
    status: int = 0


@dataclass(frozen=True, slots=True)
class MotorFeedback:
    """Motor current (A), battery voltage (V), voltage the driver applies (V);
    ``status`` bit 0 = driver enabled."""

    current: float
    vbat: float
    u_applied: float
    status: int = 0


@dataclass(frozen=True, slots=True)
class RangeReading:
    """Range to the vehicle ahead (m) with its status and MCU sample time (s, wrapping)."""

    distance: float
    status: RangeStatus
    sample_time: float = 0.0

    @property
    def valid(self) -> bool:
        """True when ``distance`` is a measurement of a target."""
        return self.status == RangeStatus.VALID

    @property
    def gap(self) -> float | None:
        """The range (m) when valid, else None."""
        return self.distance if self.status == RangeStatus.VALID else None


@dataclass(frozen=True, slots=True)
class FirmwareHeartbeat:
    """Microcontroller state, fault bits and count of rejected commands (wraps at 256)."""

    state: FirmwareState
    faults: FirmwareFault
    cmd_errors: int = 0


Message = (
    MotorCommand
    | CompanionHeartbeat
    | WheelEncoders
    | MotorFeedback
    | RangeReading
    | FirmwareHeartbeat
)
"""Any decoded message."""


def ticks_delta(new: int, old: int) -> int:
    """Signed count difference of two wrapping 16-bit encoder counts."""
    d = (new - old) % TICKS_MODULO
    return d - TICKS_MODULO if d >= TICKS_MODULO // 2 else d


def sample_time_delta(new: float, old: float) -> float:
    """Elapsed MCU time (s) between two wrapping sample times (assumes < 6.5536 s)."""
    return (new - old) % SAMPLE_TIME_MODULO
