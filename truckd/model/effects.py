"""Effects the seed model lacks (reference section 4), as physical extensions.

Each is off at its default (0).  The simulated plant switches them on; the diagnosis
fits them; an extended model written by ``diagnose`` carries them to the MPC.

========================  ==================  =============================================
name                      parameter           physics
========================  ==================  =============================================
``viscous_friction``      N m s/rad           torque ``b * omega_m`` at the motor shaft
``aero_drag``             N/(m/s)^2           force ``c * v * |v|`` at the wheels
``load_force``            N                   force opposing forward motion, independent of
                                              speed and direction (grade, towing, offset);
                                              ``load_force_amplitude`` (N) and
                                              ``load_force_wavelength`` (m) add
                                              ``A sin(2 pi x / lambda + phi)`` (rolling
                                              terrain, ``load_force_phase`` phi in rad);
                                              ``hill_force`` (N) adds a force on the
                                              stretch ``hill_start <= x < hill_start +
                                              hill_length`` (m) of the road (a hill, a bump)
``input_delay``           s                   dead time between command and actuation
``dead_zone``             V                   the driver outputs 0 for ``|u| < u_dz`` and
                                              ``u`` above (a threshold)
``dead_zone_offset``      V                   the textbook form: 0 for ``|u| < u_dz`` and
                                              ``u - sign(u) u_dz`` above (an offset)
``voltage_saturation``    V                   applied voltage clipped to ``+-u_sat``
``battery_sag``           ohm                 battery internal resistance ``R_b``: with duty
                                              ``d = u / V_batt`` the motor sees
                                              ``u - R_b d^2 i`` (supply droops with current)
``sensor_lag``            s                   measured speed low-pass filtered, time const.
``current_limit``         A                   the motor controller holds the armature
                                              current within ``+-I_max``: it lowers its
                                              voltage to ``K_v omega +- R I_max`` (torque
                                              saturates on hard acceleration and braking)
``stribeck``              N m                 sliding friction above ``K_coulomb`` at zero
                                              speed, fading as ``exp(-(v/v_s)^2)`` with
                                              ``stribeck_speed`` v_s (m/s at the wheels)
``backlash``              rad                 free angle of the drivetrain at the motor
                                              shaft: when the torque through the gears
                                              reverses, the rotor (``rotor_inertia_fraction``
                                              of ``J_S``) crosses the gap on its own while
                                              the load coasts, then hits the load
                                              (inelastic impact, momentum kept)
``resistance_drift``      K/W                 the winding's thermal resistance: copper loss
                                              ``i^2 R`` heats it (first order, time
                                              constant ``winding_time_constant`` s) and
                                              ``R = R_m (1 + alpha_Cu dT)``
========================  ==================  =============================================

Each effect's physics is written once here, as functions of the state; the plant
(:mod:`truckd.sim.plant`) and the fast simulator of the fit (:mod:`truckd.ident.fastsim`)
both call them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from truckd.model.params import VehicleParams
from truckd.schema import spec

EFFECT_NAMES: tuple[str, ...] = (
    "viscous_friction",
    "aero_drag",
    "load_force",
    "input_delay",
    "dead_zone",
    "dead_zone_offset",
    "voltage_saturation",
    "battery_sag",
    "sensor_lag",
    "current_limit",
    "backlash",
    "stribeck",
    "resistance_drift",
)
"""The effects (each switched on by its own field), in one place: the plant, the fast
simulator, the candidates of the diagnosis and the model file all follow this list."""

COMPANIONS: dict[str, tuple[str, ...]] = {
    "backlash": ("rotor_inertia_fraction",),
    "stribeck": ("stribeck_speed",),
    "resistance_drift": ("winding_time_constant",),
}
"""Fields that shape an effect beside the one that switches it on (reported with it)."""

TERRAIN_FIELDS: tuple[str, ...] = (
    "load_force_amplitude",
    "load_force_wavelength",
    "load_force_phase",
    "hill_force",
    "hill_start",
    "hill_length",
)
"""Fields of the position-dependent part of ``load_force`` (:func:`terrain_force`)."""

EFFECT_FIELDS: tuple[str, ...] = (
    *EFFECT_NAMES,
    *(c for n in EFFECT_NAMES for c in COMPANIONS.get(n, ())),
    *TERRAIN_FIELDS,
)
"""Every field of :class:`Effects`, each named once above (a test keeps the two equal)."""

COPPER_TEMPCO = 3.93e-3
"""Temperature coefficient of copper's resistance near 20 C, 1/K."""


@dataclass(frozen=True)
class Effects:
    """Parameters of the optional effects; 0 switches an effect off."""

    viscous_friction: float = spec(
        "viscous friction at the motor shaft", unit="N m s/rad", lo=0.0, hi=1.0, default=0.0
    )
    aero_drag: float = spec(
        "drag coefficient, force c v|v|", unit="N/(m/s)^2", lo=0.0, hi=100.0, default=0.0
    )
    load_force: float = spec(
        "constant force opposing forward motion", unit="N", lo=-1e3, hi=1e3, default=0.0
    )
    load_force_amplitude: float = spec(
        "amplitude of the position-dependent load force", unit="N", lo=0.0, hi=1e3, default=0.0
    )
    load_force_wavelength: float = spec(
        "wavelength of the position-dependent load force",
        unit="m",
        lo=0.0,
        lo_open=True,
        hi=1e4,
        default=10.0,
    )
    load_force_phase: float = spec(
        "phase of the position-dependent load force at x = 0",
        unit="rad",
        lo=-100.0,
        hi=100.0,
        default=0.0,
    )
    hill_force: float = spec(
        "extra force opposing forward motion on a stretch of the road (+ = uphill)",
        unit="N",
        lo=-1e3,
        hi=1e3,
        default=0.0,
    )
    hill_start: float = spec(
        "position where the hill_force stretch starts", unit="m", lo=-1e5, hi=1e5, default=0.0
    )
    hill_length: float = spec(
        "length of the hill_force stretch", unit="m", lo=0.0, hi=1e5, default=0.0
    )
    input_delay: float = spec(
        "dead time command -> actuation", unit="s", lo=0.0, hi=1.0, default=0.0
    )
    dead_zone: float = spec("driver dead zone half-width", unit="V", lo=0.0, hi=50.0, default=0.0)
    dead_zone_offset: float = spec(
        "driver dead zone half-width, subtracted above it (u - sign(u) u_dz)",
        unit="V",
        lo=0.0,
        hi=50.0,
        default=0.0,
    )
    voltage_saturation: float = spec(
        "applied-voltage clip, 0 = off (the battery voltage still limits)",
        unit="V",
        lo=0.0,
        hi=100.0,
        default=0.0,
    )
    battery_sag: float = spec(
        "battery internal resistance", unit="ohm", lo=0.0, hi=10.0, default=0.0
    )
    sensor_lag: float = spec(
        "speed sensor low-pass time constant", unit="s", lo=0.0, hi=5.0, default=0.0
    )

    current_limit: float = spec(
        "motor controller's armature current limit, 0 = off", unit="A", lo=0.0, hi=1e4, default=0.0
    )
    backlash: float = spec(
        "free angle of the drivetrain at the motor shaft, 0 = off",
        unit="rad",
        lo=0.0,
        hi=100.0,
        default=0.0,
    )
    rotor_inertia_fraction: float = spec(
        "the part of J_S on the motor's side of the backlash (rotor, pinion)",
        lo=0.0,
        lo_open=True,
        hi=0.95,
        default=0.35,
    )
    stribeck: float = spec(
        "sliding friction above K_coulomb at zero speed (Stribeck), 0 = off",
        unit="N m",
        lo=0.0,
        hi=100.0,
        default=0.0,
    )
    stribeck_speed: float = spec(
        "speed over which the Stribeck friction fades (at the wheels)",
        unit="m/s",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=0.1,
    )
    resistance_drift: float = spec(
        "winding thermal resistance (temperature rise per watt of copper loss), 0 = off",
        unit="K/W",
        lo=0.0,
        hi=100.0,
        default=0.0,
    )
    winding_time_constant: float = spec(
        "thermal time constant of the winding", unit="s", lo=0.0, lo_open=True, hi=1e5, default=60.0
    )

    def active(self) -> tuple[str, ...]:
        """Names (from :data:`EFFECT_NAMES`) of the effects switched on."""
        return tuple(n for n in EFFECT_NAMES if getattr(self, n) != 0.0)


@dataclass(frozen=True)
class Ops:
    """The few operations the driver's physics needs, on a float or on numpy arrays
    element-wise: one body of :func:`driver_output` serves the plant (one command) and
    the fast simulator of the fit (a log's commands at once)."""

    where: Callable[[Any, Any, Any], Any]
    copysign: Callable[[Any, Any], Any]
    maximum: Callable[[Any, Any], Any]
    clip: Callable[[Any, Any, Any], Any]


SCALAR = Ops(
    where=lambda c, a, b: a if c else b,
    copysign=math.copysign,
    maximum=max,
    clip=lambda u, lo, hi: max(lo, min(hi, u)),
)
"""Ops on one float (the plant)."""

ARRAYS = Ops(where=np.where, copysign=np.copysign, maximum=np.maximum, clip=np.clip)
"""Ops element-wise on numpy arrays (the fast simulator)."""


@overload
def driver_output(
    u_cmd: float, eff: Effects, v_batt: float, ops: Ops = SCALAR
) -> tuple[float, float]: ...


@overload
def driver_output(
    u_cmd: NDArray[np.float64], eff: Effects, v_batt: float, ops: Ops
) -> tuple[NDArray[np.float64], NDArray[np.float64]]: ...


def driver_output(u_cmd: Any, eff: Effects, v_batt: float, ops: Ops = SCALAR) -> tuple[Any, Any]:
    """What the motor driver makes of a voltage command (V).

    Returns ``(open-circuit voltage at the motor (V), extra series resistance (ohm))``:
    dead zone (threshold form, then offset form), then the clip at the battery voltage
    (and ``voltage_saturation``), then the battery's resistance seen through the duty cycle.
    ``u_cmd`` is a float (``ops`` :data:`SCALAR`) or an array of commands (:data:`ARRAYS`).
    """
    u = ops.where(abs(u_cmd) >= eff.dead_zone, u_cmd, 0.0)
    if eff.dead_zone_offset != 0.0:
        u = ops.copysign(ops.maximum(abs(u) - eff.dead_zone_offset, 0.0), u)
    limit = v_batt if eff.voltage_saturation == 0.0 else min(v_batt, eff.voltage_saturation)
    u = ops.clip(u, -limit, limit)
    duty = u / v_batt
    return u, eff.battery_sag * duty * duty


def position_dependent(eff: Effects) -> bool:
    """Whether the load force of ``eff`` varies with position (terrain or a hill)."""
    return eff.load_force_amplitude != 0.0 or (eff.hill_force != 0.0 and eff.hill_length > 0.0)


def terrain_force(eff: Effects, x: float) -> float:
    """The position-dependent part of the load force (N) at position x (m)."""
    force = 0.0
    if eff.load_force_amplitude != 0.0:
        phase = 2.0 * math.pi * x / eff.load_force_wavelength + eff.load_force_phase
        force += eff.load_force_amplitude * math.sin(phase)
    if eff.hill_force != 0.0 and eff.hill_start <= x < eff.hill_start + eff.hill_length:
        force += eff.hill_force
    return force


def load_torque(p: VehicleParams, eff: Effects, x: float) -> float:
    """Load torque at the motor shaft (N m) at vehicle position x (m)."""
    return p.force_to_torque(eff.load_force + terrain_force(eff, x))


def drag_linearisation(p: VehicleParams, eff: Effects, omega0: float) -> tuple[float, float]:
    """Aero drag ``c v|v|`` as torque at the motor linearised about omega0 (rad/s).

    Returns ``(viscous slope (N m s/rad), constant torque (N m))`` such that the drag
    torque is ``slope * omega + constant`` near omega0 (exact at omega0).
    """
    c = eff.aero_drag * p.ratio**3
    return 2.0 * c * abs(omega0), -c * omega0 * abs(omega0)


def current_limited(p: VehicleParams, eff: Effects, volts: float, omega: float, r: float) -> float:
    """The voltage (V) a current-limiting driver applies instead of ``volts`` at motor
    speed ``omega`` (rad/s) through the circuit resistance ``r`` (ohm): within
    ``K_v omega +- r I_max``, so that the quasi-static current stays within the limit."""
    if eff.current_limit == 0.0:
        return volts
    emf = p.K_v * omega
    room = r * eff.current_limit
    return min(max(volts, emf - room), emf + room)


def limited_torque(p: VehicleParams, eff: Effects) -> float:
    """The largest motor torque (N m) the current limit allows (inf when off)."""
    return p.K_T * eff.current_limit if eff.current_limit > 0.0 else math.inf


def stribeck_torque(p: VehicleParams, eff: Effects, omega: float) -> float:
    """Sliding friction above ``K_coulomb`` (N m, magnitude) at motor speed omega (rad/s)."""
    if eff.stribeck == 0.0:
        return 0.0
    z = omega * p.ratio / eff.stribeck_speed
    return eff.stribeck * math.exp(-z * z)


def winding_resistance(p: VehicleParams, eff: Effects, rise: float) -> float:
    """Armature resistance (ohm) with the winding ``rise`` K above where R_m was measured."""
    return p.R_m * (1.0 + COPPER_TEMPCO * rise)


def winding_rise_step(eff: Effects, rise: float, power: float, h: float) -> float:
    """Winding temperature rise (K) after h s of copper loss ``power`` (W), exactly for the
    first-order thermal model ``tau drise/dt = R_th P - rise``."""
    if eff.resistance_drift == 0.0:
        return 0.0
    e = math.exp(-h / eff.winding_time_constant)
    return rise * e + eff.resistance_drift * power * (1.0 - e)


BACKLASH_STEP = 2e-4
"""Longest step (s) of the free motion across the backlash gap (rotor exact, load at
constant deceleration over a step, the contact time interpolated within it)."""


@dataclass
class Gap:
    """State of the backlash gap.

    ``side`` +1 while the motor pushes the load forward through the gears, -1 backward,
    0 while the rotor moves freely inside the gap; ``angle`` motor angle minus load
    angle (rad, within ``+-backlash/2``); ``rotor`` the rotor's speed while free (rad/s).
    """

    side: int = 1
    angle: float = 0.0
    rotor: float = field(default=0.0)


def gap_at_start(eff: Effects, omega: float) -> Gap:
    """The gap at the start of a run at motor speed omega: closed on the side of the
    motion (forward at rest)."""
    side = -1 if omega < 0.0 else 1
    return Gap(side=side, angle=0.5 * side * eff.backlash, rotor=omega)


def gap_opens(
    p: VehicleParams,
    eff: Effects,
    gap: Gap,
    omega: float,
    volts: float,
    r: float,
    coulomb: float,
    load: float,
    viscous: float,
) -> bool:
    """Whether a closed gap opens now, at motor speed omega (rad/s) under the driver
    voltage ``volts`` through the circuit resistance ``r``: the torque through the gear
    contact pulls away from the side in contact.

    The motor torque is the quasi-static one (the current settles within ``L_m/R_m``,
    far below a sample), within the current limit; the load side resists with sliding
    friction ``coulomb``, ``load`` and ``viscous`` (N m s/rad) while moving, with up to
    ``K_stiction`` at rest.  The rotor's share of the inertia takes its share of the
    acceleration: contact torque ``(J_load T_motor + J_rotor T_resist) / J_S``."""
    motor = p.K_T * (volts - p.K_v * omega) / r
    cap = limited_torque(p, eff)
    motor = min(max(motor, -cap), cap)
    if omega != 0.0:
        resist = math.copysign(coulomb, omega) + load + viscous * omega
    else:
        resist = load + min(max(motor - load, -p.K_stiction), p.K_stiction)
    j_r = eff.rotor_inertia_fraction * p.J_S
    contact = ((p.J_S - j_r) * motor + j_r * resist) / p.J_S
    return contact * gap.side < 0.0


def gap_free_motion(
    p: VehicleParams,
    eff: Effects,
    gap: Gap,
    w_load: float,
    volts: float,
    r: float,
    coulomb: float,
    load: float,
    viscous: float,
    h: float,
) -> tuple[float, float, float]:
    """Up to h s of the rotor moving freely in an open gap (``gap.side == 0``).

    The rotor (quasi-static current ``(volts - K_v w_r) / r``) and the load (sliding
    friction ``coulomb``, ``load`` and ``viscous`` N m s/rad, all on the load side) move
    apart until the gap's other side is reached; there the two meet inelastically
    (momentum kept) and the gap closes (``gap.side`` set).  Returns ``(load speed,
    load angle travelled (rad), time used (s))``; the time used is h unless it closed.
    """
    j_r = eff.rotor_inertia_fraction * p.J_S
    j_l = p.J_S - j_r
    half = 0.5 * eff.backlash
    w_inf = volts / p.K_v
    rate = p.K_T * p.K_v / (r * j_r)
    used = 0.0
    travelled = 0.0
    while used < h:
        dt = min(BACKLASH_STEP, h - used)
        e = math.exp(-rate * dt)
        wr1 = w_inf + (gap.rotor - w_inf) * e
        ang_r = w_inf * dt + (gap.rotor - w_inf) * (1.0 - e) / rate
        if w_load != 0.0:
            s = 1.0 if w_load > 0.0 else -1.0
            dec = (s * coulomb + load + viscous * w_load) / j_l
            wl1 = w_load - dec * dt
            if wl1 * s <= 0.0 and dec * s > 0.0:
                t_stop = w_load / dec
                ang_l = 0.5 * w_load * t_stop
                wl1 = 0.0
            else:
                ang_l = 0.5 * (w_load + wl1) * dt
        elif abs(load) > p.K_stiction:
            acc = -(load - math.copysign(coulomb, load)) / j_l
            wl1 = acc * dt
            ang_l = 0.5 * wl1 * dt
        else:
            wl1, ang_l = 0.0, 0.0
        angle = gap.angle + ang_r - ang_l
        moving = angle - gap.angle
        if (angle >= half and moving > 0.0) or (angle <= -half and moving < 0.0):
            side = 1 if moving > 0.0 else -1
            frac = (side * half - gap.angle) / moving
            frac = min(max(frac, 0.0), 1.0)
            w_r = gap.rotor + frac * (wr1 - gap.rotor)
            w_l = w_load + frac * (wl1 - w_load)
            w = (j_r * w_r + j_l * w_l) / p.J_S
            gap.side, gap.angle, gap.rotor = side, side * half, w
            return w, travelled + frac * ang_l, used + frac * dt
        gap.angle, gap.rotor = angle, wr1
        w_load = wl1
        travelled += ang_l
        used += dt
    return w_load, travelled, used
