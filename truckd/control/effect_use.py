"""How the controller uses each effect of its model: one table, one entry per effect.

An effect the diagnosis names (:mod:`truckd.model.effects`) reaches the controller through
exactly one entry of :data:`EFFECT_USES`: a feedforward torque (what the MPC's model lacks,
cancelled by voltage), a term of the MPC's prediction model, an estimator term, or a map of
the command (the wanted motor voltage -> the command the driver turns into it).  An effect
present in a model but without an entry is named by :func:`unused_effects` (the daemon and
``truckd sim`` log it at start-up): nothing in a model file is silently ignored.

The command maps are pure and exact inverses of :func:`truckd.model.effects.driver_output`
where one exists:

* battery sag: the driver applies ``u - R_b (u / V_batt)^2 i`` (``i`` the motor current):
  :func:`sag_command` solves that quadratic for ``u``; without a current measurement the
  measured battery voltage gives the motor's share, ``u vbat / V_batt``.
* dead zone (threshold and offset forms): :class:`DeadZoneLaw`, the right inverse outside
  the zone and, inside it, a hysteresis between 0 V and the smallest voltage the driver
  makes, so a wanted voltage hovering at the zone's edge does not flip the command every
  cycle.

Two more pieces serve the controller's record of what acts: :func:`current_window`, the
voltages a current-limiting driver applies (``current_limit``), and :class:`Winding`, the
winding's thermal model whose resistance scales the feedforward voltages
(``resistance_drift``).  ``backlash`` has no entry (named at start-up: it costs under 2 mm
of gap error, docs/controller.md).  Pure numerics: no I/O, no clock.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

from truckd.model.effects import (
    COMPANIONS,
    Effects,
    stribeck_torque,
    terrain_force,
    winding_resistance,
    winding_rise_step,
)
from truckd.model.params import VehicleParams

Torque = Callable[[VehicleParams, Effects, float, float], float]
"""A feedforward torque term (N m at the motor shaft) at speed v (m/s) and road position x
(m, where the command will act)."""


def _drag_torque(p: VehicleParams, e: Effects, v: float, x: float) -> float:
    return p.force_to_torque(e.aero_drag * v * abs(v))


def _load_torque(p: VehicleParams, e: Effects, v: float, x: float) -> float:
    return p.force_to_torque(e.load_force)


def _terrain_torque(p: VehicleParams, e: Effects, v: float, x: float) -> float:
    return p.force_to_torque(terrain_force(e, x))


def _stribeck_torque(p: VehicleParams, e: Effects, v: float, x: float) -> float:
    """The Stribeck friction above Coulomb while moving (at rest: 0, the breakaway
    feedforward holds the zero-speed peak, :func:`breakaway_torque`)."""
    if v == 0.0:
        return 0.0
    return math.copysign(stribeck_torque(p, e, p.omega(v)), v)


def breakaway_torque(p: VehicleParams, e: Effects) -> float:
    """The static friction (N m) a start has to overcome: ``K_stiction``, or Coulomb plus
    the Stribeck peak at zero speed when that is larger (as the plant has it)."""
    return max(p.K_stiction, p.K_coulomb + stribeck_torque(p, e, 0.0))


@dataclass(frozen=True)
class EffectUse:
    """Where one effect enters the controller (``torque``: a feedforward term; ``how``:
    one line for the documentation and the start-up log)."""

    how: str
    torque: Torque | None = None


EFFECT_USES: dict[str, EffectUse] = {
    "viscous_friction": EffectUse("MPC prediction model (damping) and its steady state"),
    "aero_drag": EffectUse("feedforward torque c v|v| at the current speed", _drag_torque),
    "load_force": EffectUse("feedforward torque (constant force)", _load_torque),
    "load_force_amplitude": EffectUse(
        "feedforward torque at the position where the command acts", _terrain_torque
    ),
    "hill_force": EffectUse(
        "feedforward torque at the position where the command acts", _terrain_torque
    ),
    "input_delay": EffectUse("estimator: state predicted over the commands in the pipeline"),
    "sensor_lag": EffectUse("none needed: the speed comes from the encoders' positions"),
    "dead_zone": EffectUse("command map: right inverse with hysteresis (DeadZoneLaw)"),
    "dead_zone_offset": EffectUse("command map: offset added (DeadZoneLaw)"),
    "voltage_saturation": EffectUse("MPC input bounds at the driver's limit"),
    "battery_sag": EffectUse("command map: sag inverse from current or battery voltage"),
    "current_limit": EffectUse(
        "the voltage recorded as acting is K_v omega +- R I_max at most (no wind-up)"
    ),
    "stribeck": EffectUse(
        "feedforward torque of the Stribeck curve; breakaway at its zero-speed peak",
        _stribeck_torque,
    ),
    "resistance_drift": EffectUse(
        "feedforward voltages at the winding's resistance from its thermal model (Winding)"
    ),
}
"""Every effect the controller uses, by the :class:`~truckd.model.effects.Effects` field
that switches it on."""

COMPANION_FIELDS = frozenset(
    {"load_force_wavelength", "load_force_phase", "hill_start", "hill_length"}.union(
        *COMPANIONS.values()
    )
)
"""Fields that only shape an effect (no effect of their own): the terrain's and those the
model names beside an effect (:data:`truckd.model.effects.COMPANIONS`)."""


def present_effects(eff: Effects) -> tuple[str, ...]:
    """Every field of ``eff`` that switches an effect on (non-zero), companions excluded:
    also the fields of effects this controller does not know."""
    return tuple(
        f.name
        for f in dataclasses.fields(eff)
        if f.name not in COMPANION_FIELDS and getattr(eff, f.name) != 0.0
    )


def unused_effects(eff: Effects) -> tuple[str, ...]:
    """The effects present in ``eff`` that the controller has no use for (no table entry)."""
    return tuple(n for n in present_effects(eff) if n not in EFFECT_USES)


def startup_line(eff: Effects) -> str | None:
    """The one start-up log line naming the unused effects (None when every one is used)."""
    unused = unused_effects(eff)
    if not unused:
        return None
    return "the controller does not use these effects of its model: " + ", ".join(
        f"{n} = {getattr(eff, n):g}" for n in unused
    )


def torque_terms(eff: Effects) -> tuple[Torque, ...]:
    """The table's feedforward torque functions of the effects present in ``eff`` (the
    terrain's once although two fields switch it on)."""
    terms: list[Torque] = []
    for name in present_effects(eff):
        use = EFFECT_USES.get(name)
        if use is not None and use.torque is not None and use.torque not in terms:
            terms.append(use.torque)
    return tuple(terms)


def feedforward_torque(
    p: VehicleParams,
    eff: Effects,
    v: float,
    x: float,
    terms: tuple[Torque, ...] | None = None,
) -> float:
    """Sum of the table's feedforward torques (N m) for the effects present (``terms``:
    :func:`torque_terms` of ``eff`` when the caller keeps them, as the controller does)."""
    total = 0.0
    for term in torque_terms(eff) if terms is None else terms:
        total += term(p, eff, v, x)
    return total


def sag_command(
    u: float, r_batt: float, v_batt: float, current: float, vbat: float = math.nan
) -> float:
    """The command (V) after which a driver behind a battery of internal resistance
    ``r_batt`` (ohm, nominal voltage ``v_batt``) applies ``u`` (V) to the motor.

    The driver applies ``c - R_b (c / V_batt)^2 i`` for a command ``c`` at motor current
    ``i`` (A): the root of ``a c^2 - c + u = 0`` (``a = R_b i / V_batt^2``) nearest ``u``.
    Without a finite current, a measured battery voltage ``vbat`` (V) in
    ``(0.5, 1] V_batt`` scales the command by ``V_batt / vbat``; without either, ``u``.
    A voltage beyond what the driver can give at that current (``4 a u >= 1``) gets the
    command that gives the most, ``1 / (2 a)`` (the caller clips it to its limit).
    """
    if not math.isfinite(u) or r_batt <= 0.0:
        return u
    if math.isfinite(current):
        a = r_batt * current / (v_batt * v_batt)
        disc = 1.0 - 4.0 * a * u
        if a == 0.0:
            return u
        if disc <= 0.0:
            return 0.5 / a  # beyond the driver's reach: the command that gives the most
        return 2.0 * u / (1.0 + math.sqrt(disc))
    if math.isfinite(vbat) and 0.5 * v_batt < vbat <= v_batt:
        return u * v_batt / vbat
    return u


def sag_limit(u_max: float, r_batt: float, v_batt: float, current: float) -> float:
    """The largest motor voltage (V) a command of ``u_max`` gives at current ``current``
    (A): the plan's real upper limit (for a negative current the sag helps: ``u_max``)."""
    if r_batt <= 0.0 or not math.isfinite(current) or current <= 0.0:
        return u_max
    return u_max - r_batt * (u_max / v_batt) ** 2 * current


@dataclass
class DeadZoneLaw:
    """The command for a driver with a dead zone (both forms), with hysteresis.

    ``threshold`` (V, ``dead_zone``): the driver outputs 0 for ``|c| < threshold`` and ``c``
    above; ``offset`` (V, ``dead_zone_offset``): it outputs ``c - sign(c) offset`` beyond
    the offset.  The threshold is taken ``margin`` larger than the model says (a diagnosed
    zone is an estimate: a command just above an underestimated threshold gives 0 V); the
    smallest non-zero output relied on is ``m = max(threshold (1 + margin) - offset, 0)``
    (:attr:`smallest`).  For a wanted output ``w``:

    * ``|w| >= m``: the right inverse (``w + sign(w) offset``), exact;
    * ``|w| < m``: only 0 or ``m`` can be had.  The command switches on (to ``sign(w) m``'s
      command) when ``|w| >= on * m`` and off when ``|w| < off * m`` (``off < on``), and
      keeps its state between: a wanted voltage hovering around the middle of the zone
      holds the command instead of flipping it every cycle.
    """

    threshold: float
    offset: float = 0.0
    on: float = 0.6
    off: float = 0.3
    margin: float = 0.08
    """Relative margin on the threshold (a diagnosed 1.2 V zone came out as 1.12 V, a
    0.6 V one as 0.67 V; see docs/controller.md)."""
    _state: float = 0.0
    """The sign of the output inside the zone last cycle (0: off)."""

    @property
    def active(self) -> bool:
        return self.threshold > 0.0 or self.offset > 0.0

    @property
    def smallest(self) -> float:
        """The smallest non-zero output (V) the law relies on."""
        return max(self.threshold * (1.0 + self.margin) - self.offset, 0.0)

    def command(self, w: float) -> float:
        """The command (V) for the wanted driver output ``w`` (V)."""
        if not self.active or not math.isfinite(w):
            return w
        smallest = self.smallest
        s = math.copysign(1.0, w)
        if w == 0.0 or abs(w) < self.off * smallest:
            self._state = 0.0
            return 0.0
        if abs(w) >= smallest:
            self._state = s
            return w + s * self.offset
        if self._state != s and abs(w) < self.on * smallest:
            self._state = 0.0
            return 0.0
        self._state = s
        return s * (smallest + self.offset)

    def reset(self) -> None:
        self._state = 0.0


def current_window(p: VehicleParams, eff: Effects, omega: float, r: float) -> tuple[float, float]:
    """The motor voltages (V) a driver holding the armature current within
    ``+-current_limit`` can apply at motor speed ``omega`` (rad/s) through the circuit
    resistance ``r`` (ohm): ``K_v omega -+ r I_max`` (the whole line when off), what
    :func:`truckd.model.effects.current_limited` clips to."""
    if eff.current_limit <= 0.0 or not math.isfinite(omega):
        return -math.inf, math.inf
    emf = p.K_v * omega
    room = r * eff.current_limit
    return emf - room, emf + room


RISE_MAX = 200.0
"""The largest winding temperature rise (K) the model believes: above it the insulation
(class H, 180 C) would have burnt, so a larger one comes from a wrong current reading."""


@dataclass
class Winding:
    """The winding's temperature rise (K) from its thermal model (``resistance_drift``
    K/W, ``winding_time_constant`` s: ``tau drise/dt = R_th P - rise`` with the copper
    loss ``P = i^2 R``), started cold (rise 0), and the resistance it gives,
    ``R_m (1 + alpha_Cu rise)``.  The current is the driver's measurement when there is
    one, else the quasi-static ``(u - K_v omega) / R`` of the voltage applied; the rise
    stays within :data:`RISE_MAX`."""

    p: VehicleParams
    eff: Effects
    rise: float = 0.0

    @property
    def active(self) -> bool:
        return self.eff.resistance_drift > 0.0

    @property
    def resistance(self) -> float:
        """The winding's resistance (ohm) now."""
        return winding_resistance(self.p, self.eff, self.rise) if self.active else self.p.R_m

    def update(self, h: float, current: float, volts: float = 0.0, omega: float = 0.0) -> float:
        """Advance h s at ``current`` (A; NaN: the quasi-static current of ``volts`` V at
        ``omega`` rad/s); returns the resistance (ohm) at the end."""
        if not self.active:
            return self.p.R_m
        r = self.resistance
        i = current if math.isfinite(current) else (volts - self.p.K_v * omega) / r
        if math.isfinite(i):
            rise = winding_rise_step(self.eff, self.rise, i * i * r, h)
            self.rise = min(rise, RISE_MAX) if math.isfinite(rise) else self.rise
        return self.resistance
