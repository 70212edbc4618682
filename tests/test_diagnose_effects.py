"""Hide an effect in a plant log; diagnose must name it, recover it and gain fit.

Logs come from the reference plant (truckd.sim.plant) with random excitation, a random
magnitude (ranges in truckd.ident.synth.EFFECT_RANGES), 0.01 m/s speed noise and 0.3 A
current noise.  The seeds come from one fixed SeedSequence, not picked per case; the
hit rate over many seeds is measured by benchmarks/diagnose_bench.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from truckd.ident.api import diagnose_log
from truckd.ident.result import Diagnosis
from truckd.ident.synth import plant_log, random_effect, with_effect
from truckd.logfile import Log
from truckd.model.effects import EFFECT_NAMES, Effects
from truckd.model.params import VehicleParams

SEEDS = [int(s) for s in np.random.SeedSequence(6).generate_state(12)]
N = 5000  # 50 s at 100 Hz

# How close the recovered parameter must be: (relative, absolute).
TOLERANCE: dict[str, tuple[float, float]] = {
    "viscous_friction": (0.10, 0.0),
    "aero_drag": (0.10, 0.0),
    "load_force": (0.05, 0.2),  # N
    "input_delay": (0.0, 0.003),  # s
    "dead_zone": (0.0, 0.3),  # V: only known to between two command levels
    "voltage_saturation": (0.0, 0.1),  # V
    "battery_sag": (0.10, 0.0),
    "sensor_lag": (0.10, 0.0),
}


def _diag(p: VehicleParams, eff: Effects, seed: int) -> Diagnosis:
    return diagnose_log(plant_log(p, eff, seed=seed, n=N), p)


@pytest.mark.parametrize("k,name", list(enumerate(EFFECT_NAMES)))
def test_hidden_effect_is_named_and_recovered(params: VehicleParams, k: int, name: str) -> None:
    rng = np.random.default_rng(SEEDS[k])
    value = random_effect(name, rng)
    d = _diag(params, with_effect(name, value), int(rng.integers(1 << 30)))
    names = [f.name for f in d.effects]
    assert names == [name], f"hidden {name}={value:.4g}, named {names}"
    found = next(iter(d.effects[0].params.values()))
    rel, ab = TOLERANCE[name]
    assert abs(found - value) <= max(rel * abs(value), ab), f"{name}: {found:.4g} vs {value:.4g}"
    assert d.effects[0].fit_gain_percent > 0.2
    assert d.extended.fit_percent > d.baseline.fit_percent + 0.2
    assert not d.unexplained
    assert d.ambiguous == []


@pytest.mark.parametrize("seed", SEEDS[8:10])
def test_nothing_named_when_the_seed_explains_the_data(params: VehicleParams, seed: int) -> None:
    d = _diag(params, Effects(), seed)
    assert d.effects == []
    assert not d.unexplained
    assert d.extended.fit_percent == d.baseline.fit_percent


def test_two_effects_are_both_named(params: VehicleParams) -> None:
    rng = np.random.default_rng(SEEDS[10])
    eff = Effects(
        load_force=random_effect("load_force", rng),
        input_delay=random_effect("input_delay", rng),
    )
    d = _diag(params, eff, int(rng.integers(1 << 30)))
    assert sorted(f.name for f in d.effects) == ["input_delay", "load_force"]
    found = {f.name: next(iter(f.params.values())) for f in d.effects}
    assert found["load_force"] == pytest.approx(eff.load_force, abs=0.3)
    assert found["input_delay"] == pytest.approx(eff.input_delay, abs=0.004)


def test_disturbance_outside_the_candidates_is_unexplained(params: VehicleParams) -> None:
    """A periodic speed disturbance (e.g. a wobbling wheel) is no candidate effect."""
    seed = SEEDS[11]
    log = plant_log(params, Effects(), seed=seed, n=N)
    t = log["t"]
    cols = dict(log.columns)
    cols["v"] = log["v"] + 0.05 * np.sin(2 * np.pi * 0.37 * t + 1.0)
    d = diagnose_log(Log(cols, "wobble"), params)
    assert d.unexplained
    assert d.effects == [], f"named {[f.name for f in d.effects]} for a disturbance"


def test_viscous_friction_needs_current(params: VehicleParams) -> None:
    """Without current, viscous friction is indistinguishable from K_v: not named."""
    log = plant_log(
        params, with_effect("viscous_friction", 6e-5), seed=SEEDS[0], n=N, with_current=False
    )
    d = diagnose_log(log, params)
    assert "viscous_friction" not in [c.name for c in d.candidates]
    assert any("viscous_friction" in n for n in d.notes)
    assert d.effects == []  # K_v absorbs it; the speed is fully explained
    assert not d.unexplained
