"""Hide an effect in a plant log; diagnose must name it, recover it and gain fit.

Logs come from the reference plant (truckd.sim.plant) with random excitation, a random
magnitude (ranges in labkit.synth.EFFECT_RANGES), 0.01 m/s speed noise and 0.3 A
current noise (the causes beyond the contract's eight: tests/test_diagnose_causes.py).
The seeds come from one fixed SeedSequence, not picked per case; the
hit rate over many seeds is measured by benchmarks/diagnose_bench.py.
"""

from __future__ import annotations

import numpy as np
import pytest
from labkit.synth import plant_log, random_effect, with_effect

from truckd.ident.api import diagnose_log
from truckd.ident.result import Diagnosis
from truckd.logfile import Log
from truckd.model.effects import EFFECT_NAMES, Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

SEEDS = [int(s) for s in np.random.SeedSequence(6).generate_state(12)]
N = 5000  # 50 s at 100 Hz

# How close the recovered parameter must be: (relative, absolute).
TOLERANCE: dict[str, tuple[float, float]] = {
    "viscous_friction": (0.10, 0.0),
    "aero_drag": (0.10, 0.0),
    "load_force": (0.05, 0.2),  # N
    "input_delay": (0.0, 0.003),  # s
    "dead_zone": (0.0, 0.3),  # V: only known to between two command levels
    "dead_zone_offset": (0.0, 0.15),  # V: continuous in the width, refined by gradient
    "voltage_saturation": (0.0, 0.1),  # V
    "battery_sag": (0.10, 0.0),
    "sensor_lag": (0.10, 0.0),
}


def _diag(p: VehicleParams, eff: Effects, seed: int) -> Diagnosis:
    return diagnose_log(plant_log(p, eff, seed=seed, n=N), p)


@pytest.mark.parametrize("k,name", list(enumerate(n for n in EFFECT_NAMES if n in TOLERANCE)))
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


def test_delay_with_a_validation_log_starting_mid_motion(params: VehicleParams) -> None:
    """A separate validation log that starts while the truck moves, at a command jump.

    Delay of exactly 3 samples, current logged.  The commands before the validation
    log still act for 30 ms; simulating them as 0 V left a braking transient that
    flagged the correct model as ``unexplained`` (validation rmse 0.0125 m/s against
    0.010 m/s noise).
    """
    rng = np.random.default_rng(123)
    t = np.arange(0, 120, 0.01)
    u = np.clip(rng.uniform(-6, 6, 240).repeat(50)[: len(t)] + np.sin(2 * np.pi * 0.3 * t), -7, 7)
    cfg = PlantConfig(effects=Effects(input_delay=0.03), noise_v=0.01, seed=5)
    log = simulate_open_loop(params, t, u, cfg)
    n = len(t) // 2  # t = 60 s: the command jumps from -2.5 V to 5.5 V at 1.1 m/s
    half = [
        Log({"t": t[a:b], "u": u[a:b], "v": log.v[a:b], "i": log.i[a:b]}, name)
        for a, b, name in ((0, n, "first"), (n, len(t), "second"))
    ]
    d = diagnose_log(half[0], params, validate=half[1])
    assert [f.name for f in d.effects] == ["input_delay"]
    assert d.effects[0].params["input_delay"] == pytest.approx(0.03, abs=0.002)
    assert d.extended.rmse < 0.0105
    assert not d.unexplained
    assert d.ambiguous == []
