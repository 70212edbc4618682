"""Candidate causes (reference section 4) as parameterised extensions of the seed.

Each candidate frees one parameter of :class:`truckd.model.effects.Effects`, with a
physical scale, bounds and a grid of starting values derived from the configured
vehicle and the log's range of input and speed.  ``smooth`` says whether the fit can
refine it by gradient; a dead zone only matters through which commands it swallows, so
it is located on a grid between the log's distinct command levels.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.data import Series
from truckd.ident.terrain import Stretch, Wave
from truckd.ident.voltage import Param
from truckd.model.params import VehicleParams

MAX_LEVELS = 120
"""Most command levels a threshold (dead zone) is located between; a log whose input
varies continuously (ramps, a sine) would otherwise give one grid point per sample."""


@dataclass(frozen=True)
class Candidate:
    """One effect to try: its free parameter, starting grid and smoothness."""

    name: str
    param: Param
    grid: tuple[float, ...]
    smooth: bool = True
    needs_current: bool = False
    preset: tuple[tuple[str, float], ...] = ()
    """Effects fields set with the candidate and held (a hill's start and length, m)."""
    output: str = ""
    """Effect name (reference section 4) it reports as; default its own name."""
    extra: tuple[Param, ...] = ()
    """Further parameters freed with it when it is fitted alone (held afterwards)."""
    every_start: bool = False
    """A limit on the drive (a voltage clip, a current limit) that the seed's constants
    absorb: fitted without it, ``K_v`` and ``J_S`` move far (4x and 10x on a weak,
    heavy truck) and the grid value best on the seed's constants starts the joint fit
    in the wrong basin.  The joint fit then also starts from tighter limits of the grid
    (:func:`truckd.ident.extend.tighter_starts`; the best fit kept), when it is fitted
    alone on the seed."""


def fit_work(c: Candidate) -> float:
    """A candidate's expected fitting cost, relative (for scheduling only): one per
    parameter it frees, one more for a grid that is scanned, not refined."""
    return 1.0 + len(c.extra) + (0.0 if c.smooth else 1.0)


def hill_candidate(p0: VehicleParams, stretch: Stretch) -> Candidate:
    """A load on the located stretch of road (``load_force`` with profile hill)."""
    weight = p0.m * 9.81
    f = stretch.force
    return Candidate(
        "load_force_hill",
        Param("hill_force", max(abs(f), 0.01 * weight), -2.0 * weight, 2.0 * weight),
        tuple(sorted(float(x) for x in (0.5 * f, f, 1.5 * f))),
        preset=(("hill_start", stretch.start), ("hill_length", stretch.length)),
        output="load_force",
    )


def voltage_candidates(p0: VehicleParams, data: Series) -> list[Candidate]:
    """The contract effects for a voltage-input log (those the data can show)."""
    u_abs = np.abs(data.inp)
    u_max = float(np.max(u_abs))
    v_max = max(float(np.max(np.abs(data.v))), 0.1)
    f_c = p0.K_coulomb / p0.ratio  # Coulomb friction as a force at the wheels, N
    f_c = max(f_c, 0.1)
    b_emf = p0.K_T * p0.K_v / p0.R_m  # back-EMF damping, N m s/rad
    c_drag = f_c / v_max**2
    f_stall = p0.K_T * u_max / p0.R_m / p0.ratio  # N at the wheels
    drag_hi = min(max(50.0 * c_drag, f_stall / v_max**2), 100.0)
    h = float(np.median(np.diff(data.t)))
    levels = np.unique(np.round(u_abs[u_abs > 0], 6))
    levels = levels[levels < 0.8 * u_max]
    if len(levels) > MAX_LEVELS:  # a continuously varying input: quantiles stand in
        levels = np.unique(np.quantile(levels, np.linspace(0.0, 1.0, MAX_LEVELS)))
    mids = tuple(float(x) for x in 0.5 * (levels[1:] + levels[:-1]))
    sat_hi = min(u_max, p0.V_batt)
    out = [
        Candidate(
            "viscous_friction",
            Param("viscous_friction", b_emf, 0.0, min(20.0 * b_emf, 1.0)),
            (0.1 * b_emf, 0.5 * b_emf),
            needs_current=True,
        ),
        Candidate(
            "aero_drag",
            # At most what takes the whole stall force at the top speed seen (50 times the
            # Coulomb force there was the bound: a drag of 0.6 on a fast truck came out
            # 0.16, at that bound, with false effects beside it).
            Param("aero_drag", c_drag, 0.0, drag_hi),
            tuple(
                x for x in c_drag * np.array([0.1, 0.5, 1.0, 3.0, 10.0, 30.0, 100.0]) if x < drag_hi
            ),
        ),
        Candidate(
            "load_force",
            Param("load_force", f_c, -5.0 * f_c, 5.0 * f_c),
            (-0.5 * f_c, -0.2 * f_c, 0.2 * f_c, 0.5 * f_c),
        ),
        Candidate(
            "input_delay",
            Param("input_delay", h, 0.0, 0.5),
            # Fine start grid: the cost has local minima about a sample apart.
            tuple(
                float(x)
                for x in h
                * np.concatenate([[0.3], np.arange(0.5, 10.0, 0.5), [11.0, 13.0, 15.0, 20.0]])
            ),
        ),
        Candidate("dead_zone", Param("dead_zone", 1.0, 0.0, 0.8 * u_max), mids, smooth=False),
        # The offset form is continuous in its width: refined by gradient from a coarse grid.
        Candidate(
            "dead_zone_offset",
            Param("dead_zone_offset", 1.0, 0.0, 0.8 * u_max),
            tuple(float(x) for x in np.array([0.05, 0.1, 0.2, 0.3]) * u_max),
        ),
        Candidate(
            "voltage_saturation",
            Param("voltage_saturation", 1.0, 0.2 * sat_hi, sat_hi),
            tuple(float(x) for x in np.linspace(0.3, 0.95, 8) * sat_hi),
            every_start=True,
        ),
        Candidate(
            "battery_sag",
            Param("battery_sag", p0.R_m, 0.0, min(30.0 * p0.R_m, 10.0)),
            (0.3 * p0.R_m, 1.0 * p0.R_m, 3.0 * p0.R_m),
        ),
        Candidate(
            "sensor_lag",
            Param("sensor_lag", h, 0.0, 2.0),
            tuple(float(x) for x in h * np.array([0.5, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 15.0, 20.0])),
        ),
    ]
    out.extend(cause_candidates(p0, data))
    with_current = data.i is not None
    # A candidate without a start grid cannot be located in these data (a dead zone needs
    # two command levels below 0.8 u_max to lie between: a single step has none).
    return [c for c in out if (with_current or not c.needs_current) and c.grid]


def rolling_candidate(p0: VehicleParams, wave: Wave) -> Candidate:
    """Rolling terrain (``load_force`` with profile rolling) at the located wavelength."""
    weight = p0.m * 9.81
    a = max(wave.amplitude, 1e-3 * weight)
    lam = wave.wavelength
    return Candidate(
        "load_force_rolling",
        Param("load_force_amplitude", a, 0.0, 2.0 * weight),
        (0.5 * a, a, 1.5 * a),
        preset=(("load_force_wavelength", lam), ("load_force_phase", wave.phase)),
        output="load_force",
        extra=(
            Param("load_force_wavelength", lam, 0.8 * lam, 1.25 * lam),
            Param("load_force_phase", 1.0, wave.phase - 2.0, wave.phase + 2.0),
        ),
    )


BACKLASH_MAX_WHEEL = 0.35
"""Largest backlash (rad at the wheel, 20 degrees) a drivetrain can have and still drive."""
WINDING_RISE_MAX = 200.0
"""Largest winding temperature rise (K) a drift may imply at the log's mean copper loss:
above it the insulation (class H, 180 C) would have burnt."""


def copper_loss(p0: VehicleParams, data: Series) -> float:
    """Mean copper loss (W) in ``data``: from the logged current, else from the
    quasi-static current ``(u - K_v omega) / R_m`` of the logged speed."""
    quasi_static = (data.inp - p0.K_v * data.v / p0.ratio) / p0.R_m
    i = data.i if data.i is not None else quasi_static
    return float(np.mean(i * i)) * p0.R_m


def cause_candidates(p0: VehicleParams, data: Series) -> list[Candidate]:
    """Causes real drivetrains have beyond the contract's first eight, with bounds from
    the fitted machine ``p0`` (not the configuration) and the log's range.

    * ``current_limit`` (A): between the current that just holds Coulomb friction and
      the stall current at the largest command (no limit acts above it);
    * ``backlash`` (rad at the motor shaft): up to :data:`BACKLASH_MAX_WHEEL` at the
      wheel (the rotor's share of the inertia held at its configured fraction);
    * ``stribeck`` (``stribeck`` N m with ``stribeck_speed`` m/s freed beside
      it): up to five times the fitted Coulomb friction, fading within the speeds seen;
    * ``resistance_drift`` (K/W with ``winding_time_constant`` s freed beside it): up to
      :data:`WINDING_RISE_MAX` at the log's mean copper loss, a time constant between
      a second and ten times the log's length.
    """
    u_max = float(np.max(np.abs(data.inp)))
    v_max = max(float(np.max(np.abs(data.v))), 1e-3)
    i_stall = max(u_max / p0.R_m, 1e-6)
    i_hold = p0.K_coulomb / p0.K_T
    k_c = max(p0.K_coulomb, 1e-3 * p0.K_T * i_stall)
    duration = float(data.t[-1] - data.t[0])
    power = max(copper_loss(p0, data), 1e-9)
    drift_hi = WINDING_RISE_MAX / power
    tau0 = max(min(duration / 3.0, 120.0), 1.0)
    vs0 = 0.1 * v_max
    gearing = p0.n_g * p0.n_fd  # motor turns per wheel turn
    return [
        Candidate(
            "current_limit",
            Param("current_limit", i_stall, max(1.05 * i_hold, 0.02 * i_stall), i_stall),
            tuple(
                float(x) * i_stall
                for x in (0.15, 0.25, 0.35, 0.5, 0.65, 0.8)
                if float(x) * i_stall > 1.05 * i_hold
            ),
            every_start=True,
        ),
        Candidate(
            "backlash",
            Param("backlash", 0.02 * gearing, 0.0, BACKLASH_MAX_WHEEL * gearing),
            tuple(float(np.radians(deg)) * gearing for deg in (0.5, 1.0, 2.0, 4.0, 7.0)),
            # Held at the configured share (reported with it): the rotor's share of the
            # inertia is barely seen in the speed.
            preset=(("rotor_inertia_fraction", 0.35),),
        ),
        Candidate(
            "stribeck",
            Param("stribeck", k_c, 0.0, 5.0 * k_c),
            (0.2 * k_c, 0.5 * k_c, 1.0 * k_c, 2.0 * k_c),
            preset=(("stribeck_speed", vs0),),
            output="stribeck",
            extra=(Param("stribeck_speed", vs0, 0.005 * v_max, v_max),),
        ),
        Candidate(
            "resistance_drift",
            Param("resistance_drift", 50.0 / power, 0.0, drift_hi),
            tuple(float(x) / power for x in (10.0, 30.0, 60.0, 120.0)),
            preset=(("winding_time_constant", tau0),),
            extra=(Param("winding_time_constant", tau0, 1.0, max(10.0 * duration, 2.0)),),
        ),
    ]


def cause_problem(name: str, value: float, p: VehicleParams, runs: Sequence[Series]) -> str | None:
    """Why the new cause ``name = value`` is physically impossible for the fitted ``p``
    on these runs (None: possible, switched off, or not one of :func:`cause_candidates`)."""
    if value == 0.0:
        return None
    u_max = max(float(np.max(np.abs(r.inp))) for r in runs)
    stall = p.K_T * u_max / p.R_m
    if name == "current_limit" and p.K_T * value <= p.K_coulomb:
        return (
            f"current_limit = {value:.3g} A gives {p.K_T * value:.3g} N m, not even the "
            f"Coulomb friction {p.K_coulomb:.3g} N m: the truck could not have moved"
        )
    if name == "stribeck" and p.K_coulomb + value >= stall:
        return (
            f"friction at rest {p.K_coulomb + value:.3g} N m at or above the stall torque "
            f"at the log's largest command ({stall:.3g} N m)"
        )
    if name == "backlash" and value > BACKLASH_MAX_WHEEL * p.n_g * p.n_fd:
        return (
            f"backlash = {value:.3g} rad at the motor is {value / (p.n_g * p.n_fd):.3g} rad "
            f"at the wheel: more play than a drivetrain that drives has"
        )
    if name == "resistance_drift":
        rise = max(value * copper_loss(p, r) for r in runs)
        if rise > WINDING_RISE_MAX:
            return (
                f"resistance_drift = {value:.3g} K/W heats the winding by {rise:.3g} K at "
                f"the log's copper loss: above what its insulation survives"
            )
    return None
