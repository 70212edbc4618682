"""Candidate causes (reference section 4) as parameterised extensions of the seed.

Each candidate frees one parameter of :class:`truckd.model.effects.Effects`, with a
physical scale, bounds and a grid of starting values derived from the configured
vehicle and the log's range of input and speed.  ``smooth`` says whether the fit can
refine it by gradient; a dead zone only matters through which commands it swallows, so
it is located on a grid between the log's distinct command levels.
"""

from __future__ import annotations

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
    """The eight contract effects for a voltage-input log (those the data can show)."""
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
