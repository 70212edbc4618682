"""What the daemon has heard from the microcontroller: the latest checked messages, when
they arrived, and the raw values the supervisor and the log need.  Pure bookkeeping: the
caller passes the received messages and its clock's time.

A sensor message counts as fresh data only when its MCU sample time moved on: a message
repeating the previous sample time (a frozen sensor or a stuck firmware buffer) is counted
in ``repeated`` and ignored, so the sensor goes stale.  Non-finite fields are ignored and
counted in ``invalid``.  A range reading whose status is ``SENSOR_FAULT`` is not "no target":
it sets ``range_fault`` (the supervisor stops) and gives the estimator no sample."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

from firmware_protocol.messages import (
    TICKS_MODULO,
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
    ticks_delta,
)
from truckd.control.estimator import EncoderSample, RangeSample
from truckd.io.port import Received

NEVER = -math.inf

_TICKS = TICKS_MODULO
_HALF = TICKS_MODULO // 2
_VALID, _SENSOR_FAULT = RangeStatus.VALID, RangeStatus.SENSOR_FAULT
"""Module constants (an enum class's attribute goes through its metaclass's hook)."""


@dataclass
class SensorState:
    """Latest sensor data and arrival times (s, caller's clock)."""

    tick_len: float  # m per encoder tick
    t_any: float = NEVER
    t_encoder: float = NEVER
    t_range: float = NEVER
    encoders: list[EncoderSample] = field(default_factory=list)  # this cycle's, oldest first
    ranges: list[RangeSample] = field(default_factory=list)  # this cycle's, oldest first
    range_raw: float | None = None  # the last range value received (frozen check)
    range_valid: bool = False
    range_fault: bool = False  # the last range reading reported SENSOR_FAULT
    range_faults: int = 0  # range readings with SENSOR_FAULT
    current: float = 0.0  # A
    vbat: float = 0.0  # V
    u_fw: float = 0.0  # V the driver applies (firmware's report)
    fw_state: FirmwareState = FirmwareState.BOOT
    fw_faults: FirmwareFault = FirmwareFault.NONE
    x: float = 0.0  # m travelled (encoders)
    invalid: int = 0  # messages with non-finite fields, ignored
    repeated: int = 0  # sensor messages repeating the previous sample time (frozen), ignored
    _last_ticks: tuple[int, int] | None = None
    _range_sample_time: float | None = None
    _encoder_sample_time: float | None = None

    def update(self, now: float, received: Iterable[Received]) -> None:
        """Take this cycle's checked messages."""
        self.encoders = []
        self.ranges = []
        isfinite = math.isfinite
        for r in received:
            m = r.msg
            if isinstance(m, WheelEncoders):
                self._encoders(r.t, m)
            elif isinstance(m, RangeReading):
                distance, sample_time = m.distance, m.sample_time
                if not isfinite(distance) or not isfinite(sample_time):
                    self.invalid += 1
                    continue
                if sample_time == self._range_sample_time:
                    self.repeated += 1  # a frozen sensor: same sample again, not fresh
                    continue
                self._range_sample_time = sample_time
                valid = m.status == _VALID  # m.valid
                # A valid reading of a negative distance is no measurement: a fault.
                self.range_fault = m.status == _SENSOR_FAULT or (valid and distance < 0.0)
                if self.range_fault:
                    self.range_faults += 1
                else:
                    self.ranges.append(RangeSample(distance if valid else None, sample_time))
                self.range_raw = distance if valid else None
                self.range_valid = valid
                self.t_range = r.t
            elif isinstance(m, MotorFeedback):
                current, vbat, u_fw = m.current, m.vbat, m.u_applied
                if isfinite(current):
                    self.current = current
                if isfinite(vbat):
                    self.vbat = vbat
                if isfinite(u_fw):
                    self.u_fw = u_fw
            elif isinstance(m, FirmwareHeartbeat):
                self.fw_state, self.fw_faults = m.state, m.faults
            if r.t > self.t_any:  # max(t_any, r.t), a NaN never taken
                self.t_any = r.t

    def _encoders(self, t: float, m: WheelEncoders) -> None:
        if not math.isfinite(m.sample_time):
            self.invalid += 1
            return
        if m.sample_time == self._encoder_sample_time:
            self.repeated += 1
            return
        self._encoder_sample_time = m.sample_time
        left_ok, right_ok = not (m.status & 1), not (m.status & 2)
        self.encoders.append(
            EncoderSample(m.ticks_left, m.ticks_right, m.sample_time, left_ok, right_ok)
        )
        last = self._last_ticks
        if last is not None and (left_ok or right_ok):
            # The mean count difference of the healthy wheels (both: their sum over 2).
            if left_ok and right_ok:  # ticks_delta of each, written out (every cycle)
                dl = (m.ticks_left - last[0]) % _TICKS
                dr = (m.ticks_right - last[1]) % _TICKS
                d = (dl - _TICKS if dl >= _HALF else dl) + (dr - _TICKS if dr >= _HALF else dr)
                self.x += self.tick_len * d / 2
            elif left_ok:
                self.x += self.tick_len * ticks_delta(m.ticks_left, last[0])
            else:
                self.x += self.tick_len * ticks_delta(m.ticks_right, last[1])
        self._last_ticks = (m.ticks_left, m.ticks_right)
        if left_ok or right_ok:
            self.t_encoder = t

    def ages(self, now: float) -> dict[str, float]:
        """Seconds since the last valid message of each kind (inf: never)."""
        return {
            "link": now - self.t_any,
            "encoder": now - self.t_encoder,
            "range": now - self.t_range,
        }
