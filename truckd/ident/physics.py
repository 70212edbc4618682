"""What a truck can physically be: limits for the seed parameters and every effect.

A best fit outside these limits is reported with the reason and never accepted as a
cause.  The limits are relative to the *fitted* machine (its inertia as a mass through
the configured gearing and wheel radius, which the data cannot determine) and the log's
own time scales; the configuration is a prior: a fitted machine far from it is fitted
anyway and named in a note (:func:`configuration_notes`).  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from truckd.ident.candidates import cause_problem
from truckd.ident.data import Series
from truckd.ident.terrain import hill_problem, over_weight, rolling_problem
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

G = 9.81
"""Gravity, m/s^2."""
MASS_ROOM = 10.0
"""The fitted inertia may be this factor either way from the configured truck's before a
note says the data's machine is another one (it is fitted anyway)."""
MOTOR_ROOM = 3.0
"""... and the motor constant ``K_v`` this factor."""
DELAY_FRACTION = 0.25
"""An input delay or sensor lag longer than this fraction of the longest run is not seen."""
DELAY_MAX_S = 0.5
"""... nor one longer than this (s): a truck with more dead time is not controllable."""


def reflected_mass(p: VehicleParams) -> float:
    """The configured mass as an inertia at the motor shaft, kg m^2."""
    return p.m * p.ratio**2


def _longest_run(runs: Sequence[Series]) -> float:
    return max(float(r.t[-1] - r.t[0]) for r in runs)


def vehicle_problems(p: VehicleParams, runs: Sequence[Series]) -> list[str]:
    """Reasons why the seed parameters ``p`` are physically impossible (empty: possible)."""
    out = []
    u_max = max(float(np.max(np.abs(r.inp))) for r in runs)
    stall = p.K_T * u_max / p.R_m
    if p.K_v <= 0 or p.K_T <= 0 or p.R_m <= 0:
        out.append("motor constants must be positive")
    if p.K_coulomb >= stall:
        out.append(
            f"K_coulomb = {p.K_coulomb:.3g} N m at or above the stall torque at the log's "
            f"largest command ({stall:.3g} N m): the truck could not have moved"
        )
    return out


def fitted_mass(p: VehicleParams, p0: VehicleParams | None = None) -> float:
    """The mass (kg) of the fitted machine ``p``: the configured mass scaled by its
    inertia over the configured truck's ``p0`` (``p.m`` without ``p0``).  A machine with
    its wheels off the ground (inertia 0.002x) weighs on nothing: its loads are small."""
    return p.m if p0 is None else p.m * p.J_S / p0.J_S


def configuration_notes(p: VehicleParams, p0: VehicleParams) -> list[str]:
    """One line per way the fitted machine ``p`` differs from the configured truck ``p0``
    by more than :data:`MASS_ROOM` (inertia) or :data:`MOTOR_ROOM` (motor constant),
    with the numbers: the configuration is a prior, the data decide the machine."""
    out = []
    j = p.J_S / p0.J_S
    if not 1.0 / MASS_ROOM <= j <= MASS_ROOM:
        why = (
            "wheels off the ground, or another machine?"
            if j < 1.0
            else "a heavier load (trailer, another machine) or the gearing misconfigured?"
        )
        out.append(f"inertia {j:.3g}x the configured truck's (J_S = {p.J_S:.3g} kg m^2): {why}")
    k = p.K_v / p0.K_v
    if not 1.0 / MOTOR_ROOM <= k <= MOTOR_ROOM:
        out.append(
            f"motor constant {k:.3g}x the configured truck's (K_v = {p.K_v:.3g} V s/rad): "
            "another motor, another gearing or another supply?"
        )
    return out


def effect_problem(
    name: str,
    value: float,
    p: VehicleParams,
    runs: Sequence[Series],
    p0: VehicleParams | None = None,
) -> str | None:
    """Why ``name = value`` is physically impossible for ``p`` on these runs (None: fine).
    Limits are relative to the fitted machine: a load above the weight its inertia
    implies against the configured truck ``p0`` (:func:`fitted_mass`) is impossible."""
    mass = fitted_mass(p, p0)
    weight = mass * G
    v_max = max(float(np.max(np.abs(r.v))) for r in runs)
    u_max = max(float(np.max(np.abs(r.inp))) for r in runs)
    w_max = max(v_max / p.ratio, 1e-9)
    stall = p.K_T * u_max / p.R_m
    longest = _longest_run(runs)
    delay_max = min(DELAY_MAX_S, DELAY_FRACTION * longest)
    why = cause_problem(name, value, p, runs)  # current limit, Stribeck, drift
    if why is not None:
        return why
    if name == "load_force" and (why := over_weight("|load_force|", value, mass)):
        return why
    if name == "aero_drag" and value * v_max**2 > weight:
        return (
            f"drag at {v_max:.2g} m/s = {value * v_max**2:.3g} N exceeds the weight {weight:.3g} N"
        )
    if name == "viscous_friction" and value * w_max > stall:
        return (
            f"viscous torque at top logged speed {value * w_max:.3g} N m exceeds the stall "
            f"torque {stall:.3g} N m"
        )
    if name in ("input_delay", "sensor_lag") and value > delay_max:
        return f"{name} = {value:.3g} s longer than the log's time scales allow ({delay_max:.3g} s)"
    if name in ("dead_zone", "dead_zone_offset") and value >= u_max:
        return f"{name} = {value:.3g} V swallows every command (largest {u_max:.3g} V)"
    if name == "voltage_saturation" and value < 0.1 * u_max:
        return f"voltage_saturation = {value:.3g} V would leave the truck almost without drive"
    if name == "battery_sag" and value > max(30.0 * p.R_m, 1.0):
        return f"battery_sag = {value:.3g} ohm far above any battery's internal resistance"
    if value < 0 and name != "load_force":
        return f"{name} = {value:.3g} is negative"
    return None


def effects_problems(
    e: Effects, p: VehicleParams, runs: Sequence[Series], p0: VehicleParams | None = None
) -> list[str]:
    """Reasons for every active effect of ``e`` that is physically impossible."""
    out = []
    for name in e.active():
        why = effect_problem(name, float(getattr(e, name)), p, runs, p0)
        if why is not None:
            out.append(why)
    if e.hill_force != 0.0:
        why = hill_problem(e.hill_force, e.hill_start, e.hill_length, p, runs, fitted_mass(p, p0))
        if why is not None:
            out.append(why)
    if e.load_force_amplitude != 0.0:
        why = rolling_problem(
            e.load_force_amplitude, e.load_force_wavelength, p, runs, fitted_mass(p, p0)
        )
        if why is not None:
            out.append(why)
    return out
