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
========================  ==================  =============================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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
)


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

    def active(self) -> tuple[str, ...]:
        """Names (from :data:`EFFECT_NAMES`) of the effects switched on."""
        return tuple(n for n in EFFECT_NAMES if getattr(self, n) != 0.0)


def driver_output(u_cmd: float, eff: Effects, v_batt: float) -> tuple[float, float]:
    """What the motor driver makes of a voltage command (V).

    Returns ``(open-circuit voltage at the motor (V), extra series resistance (ohm))``:
    dead zone (threshold form, then offset form), then the clip at the battery voltage
    (and ``voltage_saturation``), then the battery's resistance seen through the duty cycle.
    """
    u = u_cmd if abs(u_cmd) >= eff.dead_zone else 0.0
    if eff.dead_zone_offset != 0.0:
        u = math.copysign(max(abs(u) - eff.dead_zone_offset, 0.0), u)
    limit = v_batt if eff.voltage_saturation == 0.0 else min(v_batt, eff.voltage_saturation)
    u = max(-limit, min(limit, u))
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
