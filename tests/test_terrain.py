"""A load on a stretch of road (a hill) is named ``load_force`` with profile hill and
located in position, on trucks unlike the configured one.

The trucks come from one fixed SeedSequence (drawn with
:func:`labkit.synth.draw_truck`: 0.1x-10x motor constant and inertia, 50-200 Hz);
the hit rate over more draws is measured by benchmarks/diagnose_bench.py.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from labkit.synth import (
    DrawnTruck,
    draw_truck,
    drawn_log,
    hill_effects,
    hill_force_for,
    rolling_effects,
)

from truckd.ident.api import diagnose_log
from truckd.ident.data import runs_from_logs, with_position
from truckd.ident.terrain import both_ways_agree, hill_problem, locate, rolling_problem
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

CHILDREN = np.random.SeedSequence(1).spawn(8)
"""Draws 1 and 4: trucks that cross the hill several times."""


def _case(params: VehicleParams, k: int) -> tuple[DrawnTruck, Effects, int]:
    rng = np.random.default_rng(CHILDREN[k])
    truck = draw_truck(params, rng)
    seed = int(rng.integers(1 << 30))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    eff = hill_effects(truck, seed, sign * hill_force_for(truck, params))
    return truck, eff, seed


@pytest.mark.parametrize("k", [1, 4])
def test_hill_is_named_located_and_recovered(params: VehicleParams, k: int) -> None:
    truck, eff, seed = _case(params, k)
    d = diagnose_log(drawn_log(truck, eff, seed), params)
    names = [f.name for f in d.effects]
    assert "aero_drag" not in names
    assert names == ["load_force"], names
    out = d.effects[0].to_json()
    assert out["profile"] == "hill"
    tol = 0.3 * eff.hill_length  # located to within 30 % of its length
    assert abs(out["x_start_m"] - eff.hill_start) < tol
    assert abs(out["x_end_m"] - (eff.hill_start + eff.hill_length)) < tol
    assert abs(out["value"] - eff.hill_force) < 0.25 * abs(eff.hill_force)
    assert d.extended.fit_percent > d.baseline.fit_percent


def test_clean_log_locates_no_hill(params: VehicleParams) -> None:
    """Without a hill the residual is not localised in position: no stretch, or one
    whose simulation-error fit is not accepted (checked by the clean-log tests)."""
    rng = np.random.default_rng(CHILDREN[4])
    truck = draw_truck(params, rng)
    seed = int(rng.integers(1 << 30))
    d = diagnose_log(drawn_log(truck, Effects(), seed), params)
    assert [f.name for f in d.effects] == []


def test_hill_residual_is_located_from_position(params: VehicleParams) -> None:
    """The equation-error locator alone finds the stretch (start within 0.5 m)."""
    truck, eff, seed = _case(params, 4)
    runs = [with_position(r) for r in runs_from_logs([drawn_log(truck, eff, seed)])]
    s = locate(params, runs)
    assert s is not None
    assert abs(s.start - eff.hill_start) < 0.5
    assert np.sign(s.force) == np.sign(eff.hill_force)


@pytest.mark.parametrize("k", [0, 2])
def test_rolling_terrain_is_named_with_its_wavelength(params: VehicleParams, k: int) -> None:
    rng = np.random.default_rng(CHILDREN[k])
    truck = draw_truck(params, rng)
    seed = int(rng.integers(1 << 30))
    rng.random()
    eff = rolling_effects(truck, seed, hill_force_for(truck, params))
    d = diagnose_log(drawn_log(truck, eff, seed), params)
    assert [f.name for f in d.effects] == ["load_force"]
    out = d.effects[0].to_json()
    assert out["profile"] == "rolling"
    assert abs(out["wavelength_m"] - eff.load_force_wavelength) < 0.1 * eff.load_force_wavelength
    assert abs(out["amplitude_n"] - eff.load_force_amplitude) < 0.25 * eff.load_force_amplitude
    assert d.extended.fit_percent > d.baseline.fit_percent


def test_impossible_terrain_is_a_finding_not_a_cause(params: VehicleParams) -> None:
    """A hill steeper than 35 % of the weight, outside the driven range or shorter than
    3 samples of travel, and rolling terrain too strong: each gets a reason."""
    rng = np.random.default_rng(CHILDREN[4])
    truck = draw_truck(params, rng)
    runs = [with_position(r) for r in runs_from_logs([drawn_log(truck, Effects(), 3)])]
    x = np.concatenate([r.x for r in runs if r.x is not None])
    mid, weight = float(np.median(x)), params.m * 9.81
    assert hill_problem(0.2 * weight, mid, 1.0, params, runs) is None
    assert "grade" in str(hill_problem(0.5 * weight, mid, 1.0, params, runs))
    assert "outside" in str(hill_problem(1.0, float(np.max(x)) + 1.0, 1.0, params, runs))
    assert "shorter" in str(hill_problem(1.0, mid, 1e-4, params, runs))
    assert rolling_problem(0.2 * weight, 2.0, params, runs) is None
    assert "grade" in str(rolling_problem(0.5 * weight, 2.0, params, runs))
    # No load exceeds the weight the fitted inertia implies, as a constant load may not:
    # on a flywheel (inertia 0.06x) a hill above the constant load refused was named.
    light = 0.1 * params.m
    assert hill_problem(0.05 * weight, mid, 1.0, params, runs, light) is None
    assert "fitted inertia" in str(hill_problem(0.2 * weight, mid, 1.0, params, runs, light))
    assert "fitted inertia" in str(rolling_problem(0.2 * weight, 2.0, params, runs, light))


def _hill_log(params: VehicleParams, rng: np.random.Generator) -> tuple[DrawnTruck, Effects, int]:
    truck = draw_truck(params, rng)
    seed = int(rng.integers(1 << 30))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    return truck, hill_effects(truck, seed, sign * hill_force_for(truck, params)), seed


@pytest.mark.parametrize("draw", [1789058713, 2349752339, 2350645654])
def test_hill_is_located_through_speed_noise(params: VehicleParams, draw: int) -> None:
    """Weak or heavy drawn trucks (motor constant 0.13x-0.8x, inertia 0.2x-3.7x: time
    constants of 1-13 s): the speed noise differentiated into the equation error buries
    the hill there; the output-error scan, with the truck's own time constant, finds it
    (edges within 30 % of its length; the force, a start for the simulation-error fit,
    within 30 %)."""
    truck, eff, seed = _hill_log(params, np.random.default_rng(draw))
    runs = [with_position(r) for r in runs_from_logs([drawn_log(truck, eff, seed)])]
    s = locate(truck.params, runs)
    assert s is not None
    tol = 0.3 * eff.hill_length
    assert abs(s.start - eff.hill_start) < tol
    assert abs(s.start + s.length - (eff.hill_start + eff.hill_length)) < tol
    assert abs(s.force - eff.hill_force) < 0.3 * abs(eff.hill_force)
    assert both_ways_agree(truck.params, runs, s.start, s.start + s.length)


def test_a_load_against_the_motion_is_no_hill(params: VehicleParams) -> None:
    """A force that opposes the motion on a stretch (a brake, or a speed term's misfit)
    has opposite signs in the two directions: not a hill (a truck that crosses the
    stretch both ways)."""
    truck, eff, seed = _hill_log(params, np.random.default_rng(1789058713))
    runs = [with_position(r) for r in runs_from_logs([drawn_log(truck, eff, seed)])]
    a, b = eff.hill_start, eff.hill_start + eff.hill_length
    assert both_ways_agree(truck.params, runs, a, b)
    flipped = []
    for r in runs:
        assert r.x is not None
        on = (r.x >= a) & (r.x < b)
        # The hill's force turned into one against the motion: seen from the command,
        # the same voltage added in the direction of travel on the stretch.
        volts = eff.hill_force * truck.params.R_m * truck.params.ratio / truck.params.K_T
        flipped.append(
            dataclasses.replace(r, inp=r.inp - np.where(on & (r.v < 0), 2.0 * volts, 0.0))
        )
    assert not both_ways_agree(truck.params, flipped, a, b)


@pytest.mark.parametrize("draw", [3887557805, 3912143785])
def test_hill_named_on_drawn_trucks_the_old_locator_missed(
    params: VehicleParams, draw: int
) -> None:
    """Diagnosed from the default configuration: named ``load_force`` with profile hill,
    edges within 30 % of its length, force within 25 %; fit raised."""
    truck, eff, seed = _hill_log(params, np.random.default_rng(draw))
    d = diagnose_log(drawn_log(truck, eff, seed), params)
    assert [f.name for f in d.effects] == ["load_force"]
    out = d.effects[0].to_json()
    assert out["profile"] == "hill"
    tol = 0.3 * eff.hill_length
    assert abs(out["x_start_m"] - eff.hill_start) < tol
    assert abs(out["x_end_m"] - (eff.hill_start + eff.hill_length)) < tol
    assert abs(out["value"] - eff.hill_force) < 0.25 * abs(eff.hill_force)
    assert d.extended.fit_percent > d.baseline.fit_percent
