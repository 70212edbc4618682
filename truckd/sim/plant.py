"""The simulated truck: the seed model plus switchable effects and sensor models.

The plant holds its own time.  ``command(u)`` sets the voltage command from now on (it
acts after ``input_delay``); ``advance(h)`` integrates exactly (see
:mod:`truckd.model.motor`), splitting the step wherever a delayed command takes effect;
``measure()`` returns what sensors would report.  Pure numerics, no clock.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from truckd.model.effects import (
    Gap,
    current_limited,
    drag_linearisation,
    driver_output,
    gap_at_start,
    gap_free_motion,
    gap_opens,
    load_torque,
    position_dependent,
    stribeck_torque,
    winding_resistance,
    winding_rise_step,
)
from truckd.model.motor import MotorState, SegmentInputs, advance
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantConfig as PlantConfig  # the plant: section


@dataclass(frozen=True)
class PlantOutput:
    """One sample of the plant's sensors.

    ``t`` s; ``v`` measured speed (m/s, with lag, quantisation and noise); ``v_true``
    m/s; ``i`` measured current (A); ``x`` true position (m); ``ticks`` encoder count
    (per wheel, unwrapped); ``vbat`` battery terminal voltage (V); ``u_applied`` the
    open-circuit voltage the driver applies (V).
    """

    t: float
    v: float
    v_true: float
    i: float
    x: float
    ticks: int
    vbat: float
    u_applied: float


FINE_STEP = 1.25e-4
"""Longest piece (s) the plant integrates at once while the current limit binds (the
driver's voltage is held over a piece); about the electrical time constant of the
default motor."""
STRIBECK_STEP = 1e-3
"""Longest piece (s) while the Stribeck friction changes with speed (held over a piece)."""
STRIBECK_SPAN = 4.0
"""Below this many Stribeck speeds the friction still changes: integrated in fine pieces."""


NOISE_BLOCK = 1024
"""Standard normal draws the sensor noise takes from its generator at a time."""


class _Normals:
    """Standard normal draws of one generator, drawn :data:`NOISE_BLOCK` at a time and
    handed out one by one: the same numbers in the same order as one draw per reading
    (``rng.normal(0, s)`` is ``s`` times the generator's next standard normal)."""

    __slots__ = ("_buf", "_k", "_rng")

    def __init__(self, rng: np.random.Generator) -> None:
        self._rng = rng
        self._buf: list[float] = []
        self._k = 0

    def next(self) -> float:
        k = self._k
        if k == len(self._buf):
            self._buf, k = self._rng.standard_normal(NOISE_BLOCK).tolist(), 0
        self._k = k + 1
        return self._buf[k]


@dataclass
class _SensorState:
    v_lag: float = 0.0
    ticks_prev: int = 0
    h_last: float = 0.0
    v_quant: float = 0.0


class Plant:
    """Simulated truck (see module docstring).  All quantities SI."""

    def __init__(self, params: VehicleParams, config: PlantConfig | None = None) -> None:
        self.p = params
        self.cfg = config or PlantConfig()
        self.rng = np.random.default_rng(self.cfg.seed)
        self._normals = _Normals(self.rng)
        self._driven = (math.nan, 0.0, 0.0)
        """The last command the driver saw and its :func:`driver_output` (V, ohm)."""
        self.t = 0.0
        self.x = 0.0
        self.motor = MotorState()
        self._u_active = 0.0
        self._pending: deque[tuple[float, float]] = deque()
        self._sensor = _SensorState()
        self._ratio = params.ratio
        eff = self.cfg.effects
        self._constant_load = eff.aero_drag == 0.0 and not position_dependent(eff)
        self._load0 = load_torque(params, eff, 0.0)
        self._inputs = SegmentInputs(voltage=0.0)
        self.winding_rise = 0.0
        """Winding temperature above where R_m was measured (K), resistance_drift."""
        self.gap: Gap = gap_at_start(eff, 0.0)
        """The backlash gap (closed forward at rest)."""
        self._tick_len = (
            2.0 * math.pi * params.r_w / self.cfg.encoder_ticks_per_rev
            if self.cfg.encoder_ticks_per_rev
            else 0.0
        )

    def reset(self, v: float = 0.0, i: float | None = None) -> None:
        """Start at speed v (m/s); current i (A), default the steady value for that speed."""
        omega = self.p.omega(v)
        if i is None:
            i = math.copysign(self.p.K_coulomb / self.p.K_T, omega) if omega else 0.0
        self.motor = MotorState(
            i=i, omega=omega, direction=(0 if omega == 0 else (1 if omega > 0 else -1))
        )
        self._sensor = _SensorState(v_lag=v, v_quant=v)
        self.gap = gap_at_start(self.cfg.effects, omega)

    def hold(self, v: float, x: float) -> None:
        """Put the truck at speed v (m/s) and position x (m), its sensors reading that
        speed from here on, keeping the motor current and the commands in the input delay
        (a truck held at a speed while its controller comes up: the platoon's pre-roll,
        :data:`truckd.sim.platoon_scenarios.PREROLL_S`)."""
        self.reset(v, self.motor.i)
        self.x = x
        self._sensor.ticks_prev = self.ticks

    @property
    def v(self) -> float:
        """True vehicle speed (m/s)."""
        return self.p.speed(self.motor.omega)

    def command(self, u: float) -> None:
        """Voltage command (V) from now on; acts after the input delay."""
        if not math.isfinite(u):
            u = 0.0  # a driver treats a non-finite command as zero
        delay = self.cfg.effects.input_delay
        if delay <= 0.0:
            self._u_active = u
            self._pending.clear()
        else:
            self._pending.append((self.t + delay, u))

    def _segment(self, h: float) -> None:
        eff = self.cfg.effects
        if eff.current_limit == 0.0 and eff.stribeck == 0.0:
            self._piece(h)
            return
        while h > 0.0:
            step = self._fine()
            piece = step if h > 1.5 * step else h
            self._piece(piece)
            h -= piece

    def _fine(self) -> float:
        """The longest piece now: shorter while the current limit binds or the Stribeck
        friction still varies (inf otherwise)."""
        eff = self.cfg.effects
        if eff.current_limit != 0.0 and self._limit_binds():
            return FINE_STEP
        if eff.stribeck != 0.0 and abs(self.v) < STRIBECK_SPAN * eff.stribeck_speed:
            return STRIBECK_STEP
        return math.inf

    def _limit_binds(self) -> bool:
        eff = self.cfg.effects
        volts, r_x = self._driver_output()
        r = self.p.R_m + r_x + self._winding_extra()
        return current_limited(self.p, eff, volts, self.motor.omega, r) != volts

    def _gap_piece(self, inputs: SegmentInputs, h: float) -> float:
        """Opens the backlash gap when the gear torque reverses and moves the rotor across
        it; returns the time (s) used before the gap closed (0 when it stays closed)."""
        p, eff, g, m = self.p, self.cfg.effects, self.gap, self.motor
        r = p.R_m + inputs.extra_resistance
        coulomb = p.K_coulomb + inputs.coulomb_extra
        load, viscous = inputs.load_torque, inputs.viscous
        if g.side != 0:
            if not gap_opens(p, eff, g, m.omega, inputs.voltage, r, coulomb, load, viscous):
                return 0.0
            g.side, g.rotor = 0, m.omega
        w, angle, used = gap_free_motion(
            p, eff, g, m.omega, inputs.voltage, r, coulomb, load, viscous, h
        )
        self.x += angle * self._ratio
        self.t += used
        m.omega = w
        m.direction = 0 if w == 0.0 else (1 if w > 0.0 else -1)
        m.i = (inputs.voltage - p.K_v * (g.rotor if g.side == 0 else w)) / r
        return used

    def _driver_output(self) -> tuple[float, float]:
        """:func:`driver_output` of the active command (V, ohm), kept while it stands."""
        u, volts, r_x = self._driven
        if u != self._u_active:
            volts, r_x = driver_output(self._u_active, self.cfg.effects, self.p.V_batt)
            self._driven = (self._u_active, volts, r_x)
        return volts, r_x

    def _winding_extra(self) -> float:
        """Resistance (ohm) the winding's heating adds to R_m."""
        if self.winding_rise == 0.0:
            return 0.0
        return winding_resistance(self.p, self.cfg.effects, self.winding_rise) - self.p.R_m

    def _piece(self, h: float) -> None:
        eff, p, motor = self.cfg.effects, self.p, self.motor
        inputs = self._inputs
        volts, r_x = self._driver_output()
        if self.winding_rise != 0.0:
            r_x += self._winding_extra()
        if eff.current_limit != 0.0:
            volts = current_limited(p, eff, volts, motor.omega, p.R_m + r_x)
        inputs.voltage, inputs.extra_resistance = volts, r_x
        inputs.coulomb_extra = stribeck_torque(p, eff, motor.omega) if eff.stribeck else 0.0
        if self._constant_load:
            inputs.load_torque = self._load0
            inputs.viscous = eff.viscous_friction
        else:
            visc_drag, t_drag = drag_linearisation(p, eff, motor.omega)
            inputs.load_torque = load_torque(p, eff, self.x) + t_drag
            inputs.viscous = eff.viscous_friction + visc_drag
        i0 = motor.i
        if eff.backlash != 0.0:
            h -= self._gap_piece(inputs, h)
        if h > 0.0:
            angle = advance(p, motor, inputs, h)
            self.x += angle * self._ratio
            self.t += h
        if eff.resistance_drift != 0.0:
            # Copper loss over the piece: the mean of the squared currents at its ends.
            r = self.p.R_m + self._winding_extra()
            power = 0.5 * (i0 * i0 + self.motor.i * self.motor.i) * r
            self.winding_rise = winding_rise_step(eff, self.winding_rise, power, h)

    def advance(self, h: float) -> None:
        """Integrate h seconds (h > 0) under the active and pending commands."""
        if not h > 0.0:
            raise ValueError(f"plant step must be positive, got {h!r}")
        end = self.t + h
        x0 = self.x
        while self._pending and self._pending[0][0] < end:
            t_apply, u = self._pending.popleft()
            if t_apply > self.t:
                self._segment(t_apply - self.t)
            self._u_active = u
        if end > self.t:
            self._segment(end - self.t)
        self.t = end
        self._update_sensors(h, (self.x - x0) / h)

    def _update_sensors(self, h: float, v_mean: float) -> None:
        s = self._sensor
        tau = self.cfg.effects.sensor_lag
        if tau > 0.0:
            s.v_lag += (1.0 - math.exp(-h / tau)) * (v_mean - s.v_lag)
        if self._tick_len:
            ticks = self.ticks
            s.v_quant = (ticks - s.ticks_prev) * self._tick_len / h
            s.ticks_prev = ticks
        s.h_last = h

    @property
    def ticks(self) -> int:
        """Encoder count of one wheel (unwrapped; 0 when the encoder is ideal)."""
        return math.floor(self.x / self._tick_len) if self._tick_len else 0

    def measure(self) -> PlantOutput:
        """What the sensors report now."""
        v, i, vbat, u_applied = self._sample()
        return PlantOutput(
            t=self.t,
            v=v,
            v_true=self.v,
            i=i,
            x=self.x,
            ticks=self.ticks,
            vbat=vbat,
            u_applied=u_applied,
        )

    def _sample(self) -> tuple[float, float, float, float]:
        """Measured speed (m/s), current (A), battery voltage (V), applied voltage (V)."""
        eff = self.cfg.effects
        s = self._sensor
        if eff.sensor_lag > 0.0:
            v = s.v_lag
        elif self._tick_len:
            v = s.v_quant
        else:
            v = self.v
        if self.cfg.noise_v:
            v += self.cfg.noise_v * self._normals.next()
        i = self.motor.i
        if self.cfg.noise_i:
            i += self.cfg.noise_i * self._normals.next()
        if (
            eff.battery_sag == 0.0
            and eff.dead_zone == 0.0
            and eff.dead_zone_offset == 0.0
            and eff.voltage_saturation == 0.0
            and eff.current_limit == 0.0
        ):
            limit = self.p.V_batt
            return v, i, limit, max(-limit, min(limit, self._u_active))
        volts, r_x = self._driver_output()
        if eff.current_limit != 0.0:
            r = self.p.R_m + r_x + self._winding_extra()
            volts = current_limited(self.p, eff, volts, self.motor.omega, r)
        duty = volts / self.p.V_batt
        vbat = self.p.V_batt - eff.battery_sag * duty * self.motor.i
        return v, i, vbat, volts - eff.battery_sag * duty * duty * self.motor.i


@dataclass
class SimulatedLog:
    """Columns of an open-loop run (numpy arrays, SI)."""

    t: np.ndarray
    u: np.ndarray
    v: np.ndarray
    i: np.ndarray
    x: np.ndarray
    vbat: np.ndarray
    v_true: np.ndarray = field(default_factory=lambda: np.zeros(0))


def simulate_open_loop(
    params: VehicleParams,
    t: np.ndarray,
    u: np.ndarray,
    config: PlantConfig | None = None,
    v0: float = 0.0,
    i0: float | None = None,
) -> SimulatedLog:
    """Run the plant on a log's input: ``u[k]`` (V) held over ``[t[k], t[k+1])``.

    Sample k of the output is the sensor reading at ``t[k]``.
    """
    plant = Plant(params, config)
    plant.reset(v=v0, i=i0)
    plant.t = float(t[0]) if len(t) else 0.0
    n = len(t)
    tl = [float(x) for x in t]
    ul = [float(x) for x in u]
    v_meas, i_meas, xs, vbat, v_true = ([0.0] * n for _ in range(5))
    for k in range(n):
        v_meas[k], i_meas[k], vbat[k], _ = plant._sample()
        xs[k], v_true[k] = plant.x, plant.motor.omega * plant._ratio
        plant.command(ul[k])
        if k + 1 < n:
            plant.advance(tl[k + 1] - tl[k])
    cols = np.array([v_meas, i_meas, xs, vbat, v_true])
    return SimulatedLog(
        t=np.asarray(t, float),
        u=np.asarray(u, float),
        v=cols[0],
        i=cols[1],
        x=cols[2],
        vbat=cols[3],
        v_true=cols[4],
    )
