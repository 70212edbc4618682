"""The simulated microcontroller: the real protocol on top of the simulated plant.

:class:`SimulatedFirmware` does what the real firmware does, in simulated time driven by
:meth:`SimulatedFirmware.step`:

- applies every valid ``MOTOR_CMD`` (checksum, counter, length checked; voltage clamped
  to the measured battery voltage; ``ENABLE`` 0 = motor off) at the start of the step;
- switches the motor off when no valid command arrived for ``cmd_timeout`` (100 ms),
  sets ``CMD_TIMEOUT`` in its heartbeat and enters ``FAILSAFE``; the next valid command
  drives again (the bit stays set until one heartbeat has reported it);
- publishes each sensor message when its period (truck.dbc) is due, with counters and
  checksums, splitting the plant step at each due time.

Run-time fault injection (:class:`FaultInjector`, or :meth:`SimulatedFirmware.apply_fault`
with a JSON-style dict): drop messages, freeze a sensor value, corrupt checksums, break
(freeze) counters, inject garbage bytes/frames, go silent, disconnect and come back.

``range_fn(t, ego_x) -> float | None`` gives the true gap to the lead (m) at time t (s)
for the ego position ego_x (m); None means no target in range.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from firmware_protocol.codec import Frame, encode, specs
from firmware_protocol.framing import MAX_PAYLOAD
from firmware_protocol.messages import (
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
from truckd.config.schema import spec
from truckd.io.inproc import Wire, inproc_pair
from truckd.io.link import FramedStreamLink, Link
from truckd.io.port import firmware_port
from truckd.model.plant_config import encoder_ticks_per_rev as encoder_ticks_per_rev
from truckd.sim.plant import Plant

RangeFn = Callable[[float, float], float | None]
"""``range_fn(t, ego_x)``: true gap to the lead (m), None when no target."""

PUBLISHED = ("WHEEL_ENCODERS", "MOTOR_FEEDBACK", "RANGE", "FIRMWARE_HEARTBEAT")
"""Messages the firmware publishes, in the order it sends them when due together."""

_EPS = 1e-9


@dataclass(frozen=True)
class FirmwareSimConfig:
    """Behaviour of the simulated microcontroller and its sensors."""

    cmd_timeout: float = spec(
        "motor off when no valid command for this long",
        unit="s",
        lo=0.001,
        hi=10.0,
        default=0.1,
    )
    ticks_per_rev: int = spec("encoder ticks per wheel revolution", lo=1, hi=65535, default=512)
    range_min: float = spec(
        "range sensor minimum distance", unit="m", lo=0.0, hi=10.0, default=0.02
    )
    range_max: float = spec(
        "range sensor maximum distance (beyond: NO_TARGET)", unit="m", lo=0.1, hi=65.0, default=4.0
    )
    range_noise: float = spec("range noise (std)", unit="m", lo=0.0, hi=1.0, default=0.0)
    undervoltage: float = spec(
        "battery voltage below which UNDERVOLTAGE is set", unit="V", lo=0.0, hi=100.0, default=5.5
    )
    seed: int = spec("random seed (range noise, garbage)", lo=0, default=0)


@dataclass
class FaultInjector:
    """Faults switchable at run time (see :meth:`SimulatedFirmware.apply_fault`).

    ``drop[name]``: frames of ``name`` still to drop (-1 = until cleared); ``freeze``:
    messages whose values stay at the last sent ones; ``bad_checksum``: messages sent
    with a wrong CHECKSUM; ``stuck_counter``: messages whose COUNTER stops advancing;
    ``garbage``: random bytes (stream links) or random frames (frame links) still to
    send; ``silent``: send nothing.
    """

    drop: dict[str, int] = field(default_factory=dict)
    freeze: set[str] = field(default_factory=set)
    bad_checksum: set[str] = field(default_factory=set)
    stuck_counter: set[str] = field(default_factory=set)
    garbage: int = 0
    silent: bool = False

    def clear(self) -> None:
        """Switch every fault off."""
        self.drop.clear()
        self.freeze.clear()
        self.bad_checksum.clear()
        self.stuck_counter.clear()
        self.garbage = 0
        self.silent = False


@dataclass
class FirmwareStats:
    """What the simulated firmware did (counts since start)."""

    commands_applied: int = 0
    cmd_timeouts: int = 0
    frames_sent: int = 0
    frames_dropped: int = 0
    garbage_sent: int = 0


class SimulatedFirmware:
    """Microcontroller emulator (see module docstring).

    ``link`` is the firmware's end of the link; ``unplug``/``replug`` are called for the
    disconnect fault (e.g. an in-process :class:`~truckd.io.inproc.Wire`'s methods).
    """

    def __init__(
        self,
        plant: Plant,
        range_fn: RangeFn,
        link: Link,
        config: FirmwareSimConfig | None = None,
        unplug: Callable[[], None] | None = None,
        replug: Callable[[], None] | None = None,
    ) -> None:
        self.plant = plant
        self.range_fn = range_fn
        self.link = link
        self.cfg = config or FirmwareSimConfig()
        self.port = firmware_port(link, clock=lambda: self.plant.t)
        self.faults = FaultInjector()
        self.stats = FirmwareStats()
        self._unplug = unplug
        self._replug = replug
        self._replug_at: float | None = None
        self._rng = random.Random(self.cfg.seed)
        self._t0 = plant.t
        p = plant.p
        self._ticks_per_m = self.cfg.ticks_per_rev / (2.0 * math.pi * p.r_w)
        s = specs()
        self._period = {n: s[n].period for n in PUBLISHED}
        self._n_sent = dict.fromkeys(PUBLISHED, 0)
        self._counter = dict.fromkeys(PUBLISHED, 0)
        self._last: dict[str, Message] = {}
        self.voltage = 0.0
        """Voltage (V) the firmware commands the driver now."""
        self.enabled = False
        self.last_command: MotorCommand | None = None
        """The last valid command received (as sent: before clamping)."""
        self._last_cmd: float | None = None
        self._timed_out = False
        self._sticky = FirmwareFault.NONE
        self._crc_seen = 0
        self._cnt_seen = 0
        plant.command(0.0)

    # -- state ---------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Firmware/plant time, s."""
        return self.plant.t

    @property
    def state(self) -> FirmwareState:
        """IDLE before the first valid command or while disabled, FAILSAFE when timed out."""
        if self._last_cmd is None:
            return FirmwareState.IDLE
        if self._timed_out:
            return FirmwareState.FAILSAFE
        return FirmwareState.ACTIVE if self.enabled else FirmwareState.IDLE

    def _cmd_errors(self) -> int:
        st = self.port.checker.stats
        return st.checksum_errors + st.length_errors + st.counter_errors + st.payload_errors

    def fault_bits(self) -> FirmwareFault:
        """Fault bits the next heartbeat reports."""
        bits = self._sticky
        if self._timed_out or (self._last_cmd is None and self.t - self._t0 > self.cfg.cmd_timeout):
            bits |= FirmwareFault.CMD_TIMEOUT
        if not self.port.checker.fresh("COMPANION_HEARTBEAT", self.t):
            bits |= FirmwareFault.COMPANION_TIMEOUT
        if self.plant.measure().vbat < self.cfg.undervoltage:
            bits |= FirmwareFault.UNDERVOLTAGE
        return bits

    # -- commands ------------------------------------------------------------------
    def _set_motor(self, voltage: float, enabled: bool) -> None:
        self.voltage = voltage
        self.enabled = enabled
        self.plant.command(voltage)

    def _receive(self) -> None:
        st = self.port.checker.stats
        for r in self.port.poll():
            if isinstance(r.msg, MotorCommand):
                v = r.msg.voltage
                limit = self.plant.measure().vbat
                if not math.isfinite(v):
                    v = 0.0
                if abs(v) > limit:
                    self._sticky |= FirmwareFault.CMD_INVALID
                    v = math.copysign(limit, v)
                self._set_motor(v if r.msg.enable else 0.0, r.msg.enable)
                self.last_command = r.msg
                self._last_cmd = r.t
                self._timed_out = False
                self.stats.commands_applied += 1
        if st.checksum_errors or st.length_errors or st.payload_errors:
            n = st.checksum_errors + st.length_errors + st.payload_errors
            if n != self._crc_seen:
                self._sticky |= FirmwareFault.CMD_CHECKSUM
                self._crc_seen = n
        if st.counter_errors + st.counter_gaps != self._cnt_seen:
            self._sticky |= FirmwareFault.CMD_COUNTER
            self._cnt_seen = st.counter_errors + st.counter_gaps

    def _timeout_at(self) -> float:
        base = self._last_cmd if self._last_cmd is not None else math.inf
        return base + self.cfg.cmd_timeout

    def _check_timeout(self) -> None:
        if (
            not self._timed_out
            and self._last_cmd is not None
            and (self.t >= self._timeout_at() - _EPS)
        ):
            self._timed_out = True
            self._sticky |= FirmwareFault.CMD_TIMEOUT
            self.stats.cmd_timeouts += 1
            self._set_motor(0.0, False)

    # -- stepping ------------------------------------------------------------------
    def _next_due(self, name: str) -> float:
        return self._t0 + self._n_sent[name] * self._period[name]

    def step(self, dt: float) -> None:
        """Advance ``dt`` s (> 0): apply received commands, run the plant, publish."""
        if not dt > 0.0 or not math.isfinite(dt):
            raise ValueError(f"firmware step must be positive and finite, got {dt!r}")
        t_end = self.t + dt
        self._receive()
        self._check_timeout()
        self._publish_due()
        while self.t < t_end - _EPS:
            nxt = min(min(self._next_due(n) for n in PUBLISHED), t_end)
            if not self._timed_out:
                nxt = min(nxt, max(self._timeout_at(), self.t))
            if self._replug_at is not None:
                nxt = min(nxt, max(self._replug_at, self.t))
            if nxt > self.t + _EPS:
                self.plant.advance(nxt - self.t)
            else:  # defensive: never spin on an event that is already handled
                self.plant.advance(t_end - self.t)
            self._check_timeout()
            self._check_replug()
            self._publish_due()

    def _check_replug(self) -> None:
        if self._replug_at is not None and self.t >= self._replug_at - _EPS:
            self._replug_at = None
            if self._replug is not None:
                self._replug()

    def _publish_due(self) -> None:
        for name in PUBLISHED:
            while self._next_due(name) <= self.t + _EPS:
                self._n_sent[name] += 1
                self._publish(name)
        if self.faults.garbage > 0 and not self.faults.silent:
            self._send_garbage()

    # -- messages ------------------------------------------------------------------
    def _make(self, name: str) -> Message:
        t = self.t
        if name == "WHEEL_ENCODERS":
            ticks = math.floor(self.plant.x * self._ticks_per_m)
            return WheelEncoders(ticks, ticks, t - self._t0, 0)
        if name == "MOTOR_FEEDBACK":
            m = self.plant.measure()
            return MotorFeedback(m.i, m.vbat, m.u_applied, int(self.enabled))
        if name == "RANGE":
            gap = self.range_fn(t, self.plant.x)
            if gap is None or not math.isfinite(gap) or gap > self.cfg.range_max:
                return RangeReading(0.0, RangeStatus.NO_TARGET, t - self._t0)
            if self.cfg.range_noise:
                gap += self._rng.gauss(0.0, self.cfg.range_noise)
            return RangeReading(max(gap, self.cfg.range_min), RangeStatus.VALID, t - self._t0)
        bits = self.fault_bits()
        self._sticky = FirmwareFault.NONE
        return FirmwareHeartbeat(self.state, bits, self._cmd_errors())

    def _publish(self, name: str) -> None:
        f = self.faults
        msg = self._last[name] if name in f.freeze and name in self._last else self._make(name)
        self._last[name] = msg
        counter = self._counter[name]
        if name not in f.stuck_counter:
            self._counter[name] = (counter + 1) & 0xF
        if f.silent:
            return
        left = f.drop.get(name, 0)
        if left != 0:
            if left > 0:
                f.drop[name] = left - 1
            self.stats.frames_dropped += 1
            return
        frame = encode(msg, counter)
        if name in f.bad_checksum:
            frame = Frame(frame.can_id, frame.data[:-1] + bytes((frame.data[-1] ^ 0xA5,)))
        if self.link.send(frame):
            self.stats.frames_sent += 1

    def _send_garbage(self) -> None:
        n = self.faults.garbage
        self.faults.garbage = 0
        rng = self._rng
        if isinstance(self.link, FramedStreamLink):
            self.link.send_raw(bytes(rng.randrange(256) for _ in range(n)))
        else:
            for _ in range(n):
                data = bytes(rng.randrange(256) for _ in range(rng.randrange(MAX_PAYLOAD + 1)))
                self.link.send(Frame(rng.randrange(0x800), data))
        self.stats.garbage_sent += n

    # -- faults --------------------------------------------------------------------
    def disconnect(self, duration: float) -> None:
        """Unplug now and plug back in after ``duration`` s of simulated time."""
        if self._unplug is None:
            raise ValueError("this firmware has no unplug hook for the disconnect fault")
        self._unplug()
        self._replug_at = self.t + max(duration, 0.0)

    def apply_fault(self, cmd: Mapping[str, Any]) -> None:
        """Switch a fault from a JSON-style command; ValueError when malformed.

        ``{"fault": "drop", "message": NAME, "count": N}`` (count -1 or absent = until
        cleared, 0 = stop dropping); ``{"fault": "freeze"|"checksum"|"counter",
        "message": NAME, "on": bool}``; ``{"fault": "garbage", "bytes": N}``;
        ``{"fault": "silent", "on": bool}``; ``{"fault": "disconnect", "duration": S}``;
        ``{"fault": "clear"}``.  NAME is one of :data:`PUBLISHED`.
        """
        kind = cmd.get("fault")
        f = self.faults
        if kind == "clear":
            f.clear()
            return
        if kind == "silent":
            f.silent = bool(cmd.get("on", True))
            return
        if kind == "garbage":
            n = cmd.get("bytes", 64)
            if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n <= 1_000_000:
                raise ValueError(f"garbage: 'bytes' must be an integer 0..1e6, got {n!r}")
            f.garbage += n
            return
        if kind == "disconnect":
            d = cmd.get("duration", 0.5)
            if not isinstance(d, int | float) or not 0 <= d <= 3600:
                raise ValueError(f"disconnect: 'duration' must be 0..3600 s, got {d!r}")
            self.disconnect(float(d))
            return
        if kind not in ("drop", "freeze", "checksum", "counter"):
            raise ValueError(
                f"unknown fault {kind!r}; expected drop, freeze, checksum, counter, garbage, "
                "silent, disconnect or clear"
            )
        name = cmd.get("message")
        if name not in PUBLISHED:
            raise ValueError(f"{kind}: 'message' must be one of {PUBLISHED}, got {name!r}")
        if kind == "drop":
            count = cmd.get("count", -1)
            if not isinstance(count, int) or isinstance(count, bool) or count < -1:
                raise ValueError(f"drop: 'count' must be an integer >= -1, got {count!r}")
            f.drop[name] = count
            return
        sets = {"freeze": f.freeze, "checksum": f.bad_checksum, "counter": f.stuck_counter}
        if cmd.get("on", True):
            sets[kind].add(name)
        else:
            sets[kind].discard(name)


def constant_speed_lead(gap0: float, v_lead: float) -> RangeFn:
    """Built-in lead: starts ``gap0`` m ahead of x = 0 and drives at ``v_lead`` m/s."""

    def range_fn(t: float, ego_x: float) -> float | None:
        return gap0 + v_lead * t - ego_x

    return range_fn


def simulated_truck(
    plant: Plant,
    range_fn: RangeFn,
    mode: Literal["frames", "bytes"] = "frames",
    config: FirmwareSimConfig | None = None,
) -> tuple[Link, SimulatedFirmware, Wire]:
    """A simulated firmware on an in-process pair: (companion link, firmware, wire).

    The disconnect fault unplugs the wire.  Drive it with ``firmware.step(dt)``.
    """
    companion, mcu, wire = inproc_pair(mode)
    fw = SimulatedFirmware(plant, range_fn, mcu, config, wire.disconnect, wire.reconnect)
    return companion, fw, wire
