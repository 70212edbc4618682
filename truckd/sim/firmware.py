"""The simulated microcontroller: the C firmware core on top of the simulated plant.

The firmware logic is the microcontroller's own code, ``firmware_protocol/firmware/``
(C99), loaded through ctypes (:mod:`firmware_protocol.fwcore`).  :class:`SimulatedFirmware`
is its board: the hardware abstraction layer on the simulated plant (encoders from the
plant position, current and battery from ``plant.measure()``, range from ``range_fn``,
the motor voltage into ``plant.command``), a millisecond clock from the plant's time, and
the link.  In simulated time driven by :meth:`SimulatedFirmware.step`, the C core:

- applies every valid ``MOTOR_CMD`` (checksum, counter, length, value range checked;
  voltage clamped to the measured battery voltage; ``ENABLE`` 0 = motor off) at the
  start of the step;
- switches the motor off when no valid command arrived for ``cmd_timeout`` (100 ms),
  sets ``CMD_TIMEOUT`` in its heartbeat and enters ``FAILSAFE``; the next valid command
  drives again (the bit stays set until one heartbeat has reported it);
- publishes each sensor message when its period (truck.dbc) is due, with counters and
  checksums; the plant step is split at each due time and at the timeout instant.

Run-time fault injection (:meth:`SimulatedFirmware.apply_fault` with a JSON-style dict):
drop messages, freeze a message's values, corrupt checksums, break (freeze) counters and
go silent are the C core's test hooks; garbage bytes/frames and disconnect-and-come-back
happen here, on the link.

``range_fn(t, ego_x) -> float | None`` gives the true gap to the lead (m) at time t (s)
for the ego position ego_x (m); None means no target in range.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from firmware_protocol.codec import Frame
from firmware_protocol.framing import MAX_PAYLOAD
from firmware_protocol.fwcore import (
    RANGE_NO_TARGET,
    RANGE_VALID,
    TX_BAD_CHECKSUM,
    TX_FREEZE,
    TX_STUCK_COUNTER,
    CoreConfig,
    FirmwareCore,
)
from firmware_protocol.messages import FirmwareFault, FirmwareState, MotorCommand
from firmware_protocol.timing import limits, timing
from truckd.io.config import ENCODER_TICKS_PER_REV
from truckd.io.inproc import Wire, inproc_pair
from truckd.io.link import FramedStreamLink, Link
from truckd.model.plant_config import encoder_ticks_per_rev as encoder_ticks_per_rev
from truckd.schema import spec
from truckd.sim.plant import Plant

RangeFn = Callable[[float, float], float | None]
"""``range_fn(t, ego_x)``: true gap to the lead (m), None when no target."""

PUBLISHED = ("WHEEL_ENCODERS", "MOTOR_FEEDBACK", "RANGE", "FIRMWARE_HEARTBEAT")
"""Messages the firmware publishes, in the order it sends them when due together."""

_EPS = 1e-9
_MS_EPS = 1e-6  # ms: plant times a float rounding below a whole millisecond count as it


@dataclass(frozen=True)
class FirmwareSimConfig:
    """Behaviour of the simulated microcontroller and its sensors."""

    cmd_timeout: float = spec(
        "motor off when no valid command for this long (truck.dbc: MOTOR_CMD's TruckTimeoutTime)",
        unit="s",
        lo=0.001,
        hi=10.0,
        default=timing().cmd_timeout,
    )
    ticks_per_rev: int = spec(
        "encoder ticks per wheel revolution (link.encoder_ticks_per_rev)",
        lo=1,
        hi=65535,
        default=ENCODER_TICKS_PER_REV,
    )
    range_min: float = spec(
        "range sensor minimum distance (truck.dbc: TruckRangeMinMm)",
        unit="m",
        lo=0.0,
        hi=10.0,
        default=limits().range_min,
    )
    range_max: float = spec(
        "range sensor maximum distance (beyond: NO_TARGET; truck.dbc: TruckRangeMaxMm)",
        unit="m",
        lo=0.1,
        hi=65.0,
        default=limits().range_max,
    )
    range_noise: float = spec(
        "range noise (std; a real time-of-flight sensor has a few mm, and a value that "
        "never changes is a frozen sensor to the supervisor)",
        unit="m",
        lo=0.0,
        hi=1.0,
        default=0.002,
    )
    undervoltage: float = spec(
        "battery voltage below which UNDERVOLTAGE is set (truck.dbc: TruckUndervoltageMv)",
        unit="V",
        lo=0.0,
        hi=100.0,
        default=limits().undervoltage,
    )
    seed: int = spec("random seed (range noise, garbage)", lo=0, default=0)


@dataclass
class FaultInjector:
    """Faults switched on now (a mirror of what :meth:`SimulatedFirmware.apply_fault` set;
    drop counts are counted down in the C core, see ``stats.frames_dropped``)."""

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


def _mv(volts: float) -> int:
    """V -> mV, non-finite as 0 (an ADC never reads NaN)."""
    return round(volts * 1000.0) if math.isfinite(volts) else 0


class SimulatedFirmware:
    """The C firmware core on the simulated plant (see module docstring).

    ``link`` is the firmware's end of the link: a byte-stream link
    (:class:`~truckd.io.link.FramedStreamLink`: serial framing, done by the C core) or a
    frame link (CAN); ``unplug``/``replug`` are called for the disconnect fault (e.g. an
    in-process :class:`~truckd.io.inproc.Wire`'s methods).
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
        self.faults = FaultInjector()
        self._garbage_sent = 0
        self._unplug = unplug
        self._replug = replug
        self._replug_at: float | None = None
        self._rng = random.Random(self.cfg.seed)
        self._t0 = plant.t
        self._ticks_per_m = self.cfg.ticks_per_rev / (2.0 * math.pi * plant.p.r_w)
        self._stream = isinstance(link, FramedStreamLink)
        self._reconnects = link.stats.reconnects
        self.voltage = 0.0
        """Voltage (V) the firmware commands the driver now."""
        self.enabled = False
        c = self.cfg
        self.core = FirmwareCore(
            self,
            CoreConfig(
                link="serial" if self._stream else "can",
                cmd_timeout_ms=max(1, round(c.cmd_timeout * 1000.0)),
                undervoltage_mv=_mv(c.undervoltage),
                range_min_mm=round(c.range_min * 1000.0),
                range_max_mm=round(c.range_max * 1000.0),
            ),
        )
        """The C firmware (:class:`~firmware_protocol.fwcore.FirmwareCore`)."""

    # -- the HAL (called back from C) ----------------------------------------------------
    def read_encoders(self) -> tuple[int, int, int]:
        """Both wheels from the plant position (the plant has one wheel speed), through
        the plant's wiring (``plant.wiring``: encoder sign and counts scale)."""
        w = self.plant.cfg.wiring
        counts = w.encoder_sign * w.counts_scale * self.plant.x * self._ticks_per_m
        ticks = math.floor(counts) & 0xFFFF
        return ticks, ticks, 0

    def read_power(self) -> tuple[int, int, int]:
        """Plant current, battery and applied voltage, in mA and mV, as the driver sees
        them (its current sense and output are on the bridge's side of swapped leads)."""
        m = self.plant.measure()
        sign = self.plant.cfg.wiring.motor_sign
        return _mv(sign * m.i), _mv(m.vbat), _mv(sign * m.u_applied)

    def read_range(self) -> tuple[int, int]:
        """``range_fn`` at the plant's time and position (+ noise), in mm."""
        gap = self.range_fn(self.t, self.plant.x)
        if gap is None or not math.isfinite(gap) or gap > self.cfg.range_max:
            return RANGE_NO_TARGET, 0
        if self.cfg.range_noise:
            gap += self._rng.gauss(0.0, self.cfg.range_noise)
        return RANGE_VALID, round(max(gap, -1e6) * 1000.0)

    def set_motor(self, voltage_mv: int, enable: bool) -> None:
        """The driver: the plant gets the voltage (0 V when disabled: braking)."""
        self.voltage = voltage_mv / 1000.0 if enable else 0.0
        self.enabled = enable
        self.plant.command(self.plant.cfg.wiring.motor_sign * self.voltage)  # leads swapped: -1

    def send_bytes(self, data: bytes) -> bool:
        """Serial wire bytes from the core."""
        assert isinstance(self.link, FramedStreamLink)
        return self.link.send_raw(data)

    def send_frame(self, can_id: int, data: bytes) -> bool:
        """A CAN frame from the core."""
        return self.link.send(Frame(can_id, data))

    # -- state ---------------------------------------------------------------------------
    @property
    def t(self) -> float:
        """Firmware/plant time, s."""
        return self.plant.t

    def _sync_clock(self) -> None:
        self.core.now_ms = math.floor((self.plant.t - self._t0) * 1000.0 + _MS_EPS)

    @property
    def state(self) -> FirmwareState:
        """IDLE before the first valid command or while disabled, FAILSAFE when timed out."""
        return FirmwareState(self.core.state)

    def fault_bits(self) -> FirmwareFault:
        """Fault bits the next heartbeat reports."""
        self._sync_clock()
        return FirmwareFault(self.core.fault_bits())

    @property
    def last_command(self) -> MotorCommand | None:
        """The last valid command received (as sent: before clamping)."""
        last = self.core.last_command()
        return None if last is None else MotorCommand(last[0] / 1000.0, last[1])

    @property
    def stats(self) -> FirmwareStats:
        """What the firmware did (from the C core, plus the garbage sent here)."""
        fw = self.core.stats()["fw"]
        return FirmwareStats(
            commands_applied=fw["commands_applied"],
            cmd_timeouts=fw["cmd_timeouts"],
            frames_sent=fw["frames_sent"],
            frames_dropped=fw["frames_dropped"],
            garbage_sent=self._garbage_sent,
        )

    def link_stats(self) -> dict[str, int | bool]:
        """The firmware end's counters, flat (like ``Port.stats()``): the link's, the C
        core's receive checks (``rx_*``) and, on serial, its deframer (``framing_*``)."""
        self._sync_clock()
        self.core.rx_fresh("MOTOR_CMD")  # counts a pending timeout
        self.core.rx_fresh("COMPANION_HEARTBEAT")
        st = self.core.stats()
        d: dict[str, int | bool] = {"connected": self.link.connected}
        d.update({k: v for k, v in self.link.stats.as_dict().items() if k[:8] != "framing_"})
        d.update({f"rx_{k}": v for k, v in st["rx"].items()})
        if self._stream:
            d.update({f"framing_{k}": v for k, v in st["framing"].items()})
        return d

    # -- stepping ------------------------------------------------------------------------
    def _receive(self) -> None:
        self._sync_clock()
        link = self.link
        if isinstance(link, FramedStreamLink):
            data = link.recv_raw(0.0)
            if link.stats.reconnects != self._reconnects:
                self._reconnects = link.stats.reconnects
                self.core.link_reset()  # a partial frame from before the outage is gone
            self.core.rx_bytes(data)
            return
        while (frame := link.recv(0.0)) is not None:
            self.core.rx_frame(frame.can_id, frame.data)

    def step(self, dt: float) -> None:
        """Advance ``dt`` s (> 0): apply received commands, run the plant, publish."""
        if not dt > 0.0 or not math.isfinite(dt):
            raise ValueError(f"firmware step must be positive and finite, got {dt!r}")
        plant = self.plant
        t_end = plant.t + dt
        self._receive()
        self._poll()
        while plant.t < t_end - _EPS:
            nxt = min(self._t0 + self.core.next_event() / 1000.0, t_end)
            if self._replug_at is not None:
                nxt = min(nxt, max(self._replug_at, plant.t))
            if nxt > plant.t + _EPS:
                plant.advance(nxt - plant.t)
            else:  # defensive: never spin on an event that is already handled
                plant.advance(t_end - plant.t)
            self._check_replug()
            self._poll()

    def _poll(self) -> None:
        self._sync_clock()
        self.core.poll()
        if self.faults.garbage > 0 and not self.faults.silent:
            self._send_garbage()

    def _check_replug(self) -> None:
        if self._replug_at is not None and self.t >= self._replug_at - _EPS:
            self._replug_at = None
            if self._replug is not None:
                self._replug()

    def _send_garbage(self) -> None:
        n = self.faults.garbage
        self.faults.garbage = 0
        rng = self._rng
        line_garbage = getattr(self.link, "send_garbage", None)  # e.g. an slcan adapter
        if isinstance(self.link, FramedStreamLink):
            self.link.send_raw(bytes(rng.randrange(256) for _ in range(n)))
        elif callable(line_garbage):
            line_garbage(rng, n)
        else:
            for _ in range(n):
                data = bytes(rng.randrange(256) for _ in range(rng.randrange(MAX_PAYLOAD + 1)))
                self.link.send(Frame(rng.randrange(0x800), data))
        self._garbage_sent += n

    # -- faults --------------------------------------------------------------------------
    def disconnect(self, duration: float) -> None:
        """Unplug now and plug back in after ``duration`` s of simulated time."""
        if self._unplug is None:
            raise ValueError("this firmware has no unplug hook for the disconnect fault")
        self._unplug()
        self._replug_at = self.t + max(duration, 0.0)

    def _push_tx_faults(self, name: str) -> None:
        f = self.faults
        bits = (
            (TX_FREEZE if name in f.freeze else 0)
            | (TX_BAD_CHECKSUM if name in f.bad_checksum else 0)
            | (TX_STUCK_COUNTER if name in f.stuck_counter else 0)
        )
        self.core.set_tx_fault(name, bits)

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
            self.core.clear_faults()
            return
        if kind == "silent":
            f.silent = bool(cmd.get("on", True))
            self.core.set_silent(f.silent)
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
            if not isinstance(count, int) or isinstance(count, bool) or not -1 <= count < 2**31:
                raise ValueError(f"drop: 'count' must be an integer >= -1, got {count!r}")
            f.drop[name] = count
            self.core.set_drop(name, count)
            return
        sets = {"freeze": f.freeze, "checksum": f.bad_checksum, "counter": f.stuck_counter}
        if cmd.get("on", True):
            sets[kind].add(name)
        else:
            sets[kind].discard(name)
        self._push_tx_faults(name)


def constant_speed_lead(gap0: float, v_lead: float) -> RangeFn:
    """Built-in lead: starts ``gap0`` m ahead of x = 0 and drives at ``v_lead`` m/s."""

    def range_fn(t: float, ego_x: float) -> float | None:
        return gap0 + v_lead * t - ego_x

    return range_fn


class CuedLead:
    """A lead ``gap0`` m ahead of x = 0, standing until :meth:`go`, then at ``v_lead`` m/s
    (a ``RangeFn``).  For a rig whose daemon starts seconds after its plant (a loaded
    machine): a lead driving from t = 0 could leave the sensor's range before anyone
    follows it."""

    def __init__(self, gap0: float, v_lead: float) -> None:
        self.gap0, self.v_lead = gap0, v_lead
        self.t_go = math.inf
        """Plant time (s) the lead set off (inf: standing)."""

    def go(self, t: float) -> None:
        """Set off at plant time ``t`` (s); later calls change nothing."""
        if self.t_go == math.inf:
            self.t_go = t

    def __call__(self, t: float, ego_x: float) -> float | None:
        return self.gap0 + self.v_lead * max(t - self.t_go, 0.0) - ego_x


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
