"""A load on a stretch of road (a hill) is named ``load_force`` with profile hill and
located in position, on trucks unlike the configured one.

The trucks come from one fixed SeedSequence (drawn with
:func:`truckd.ident.synth.draw_truck`: 0.1x-10x motor constant and inertia, 50-200 Hz);
the hit rate over more draws is measured by benchmarks/diagnose_bench.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from truckd.ident.api import diagnose_log
from truckd.ident.data import runs_from_logs, with_position
from truckd.ident.synth import (
    DrawnTruck,
    draw_truck,
    drawn_log,
    hill_effects,
    hill_force_for,
    rolling_effects,
)
from truckd.ident.terrain import hill_problem, locate, rolling_problem
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
