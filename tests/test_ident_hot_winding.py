"""A winding heated by 150-200 K: the fast simulator's passes converge on the plant's
heating, and the diagnosis names the drift and recovers it.

A small motor (0.1x-0.35x the default motor constant) draws a large current for long:
its winding heats by up to the 200 K its insulation survives, and its resistance nearly
doubles. The C kernel steps the heating beside the speed in one run; without it the fast
simulator finds the heating by passes (each simulates the run with the resistance the
previous one's current made) until they converge. A fixed two passes left such a run far
from the plant (a free-run fit of 77 % for the true model), and the drift went unnamed.
Trucks and magnitudes are drawn from a fixed seed until the hidden drift heats the
winding that much (a condition, not a seed picked per case).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from labkit.synth import DrawnTruck, draw_truck, drawn_log, excitation, random_effects

from truckd.ident import ckernel, fastsim, freerun
from truckd.ident.api import diagnose_log
from truckd.ident.fastsim import simulate_voltage, winding_rises
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

SEED = 20261202
SECONDS = 50.0
RISE_LO, RISE_HI = 150.0, 200.0
"""The hottest winding wanted (K above where R_m was measured) over the log."""


def _hot(p: VehicleParams) -> tuple[DrawnTruck, Effects, int]:
    """A drawn truck, a hidden drift and the log's seed whose winding heats by
    :data:`RISE_LO` to :data:`RISE_HI` over the log (from the plant's own current)."""
    rng = np.random.default_rng(SEED)
    for _ in range(400):
        truck = draw_truck(p, rng)
        eff = random_effects("resistance_drift", rng, truck.k_scale)
        log_seed = int(rng.integers(1 << 30))
        if truck.k_scale > 0.35:  # too strong a motor to heat that much
            continue
        log = drawn_log(truck, eff, log_seed, SECONDS, with_current=True)
        top = float(np.max(winding_rises(truck.params, eff, log["t"], log["i"], 0.0)))
        if RISE_LO <= top <= RISE_HI:
            return truck, eff, log_seed
    raise AssertionError("no drawn truck heats its winding by 150-200 K")


@pytest.fixture(scope="module")
def hot(params: VehicleParams) -> tuple[DrawnTruck, Effects, int]:
    return _hot(params)


def test_the_fast_run_of_a_hot_winding_is_the_plants(
    hot: tuple[DrawnTruck, Effects, int],
) -> None:
    """The true model's fast free run on the plant's input, without noise: its speed
    within 1 % (RMS, of the speed's RMS) of the plant's, and its heating the plant's."""
    truck, eff, log_seed = hot
    rng = np.random.default_rng(log_seed)
    t, u = excitation(rng, int(SECONDS * truck.rate_hz), h=1.0 / truck.rate_hz)
    plant = simulate_open_loop(truck.params, t, u, PlantConfig(effects=eff, seed=log_seed))
    fast = simulate_voltage(truck.params, eff, t, u)
    err = float(np.sqrt(np.mean((fast.v - plant.v) ** 2)) / np.sqrt(np.mean(plant.v**2)))
    assert err < 0.01, f"k={truck.k_scale:.3g}: speed off the plant's by {100 * err:.2f} %"
    rise_plant = winding_rises(truck.params, eff, t, plant.i, 0.0)
    rise_fast = winding_rises(truck.params, eff, t, fast.i, 0.0)
    assert float(np.max(np.abs(rise_fast - rise_plant))) < 0.02 * float(np.max(rise_plant))
    cold = simulate_voltage(truck.params, dataclasses.replace(eff, resistance_drift=0.0), t, u)
    assert float(np.sqrt(np.mean((cold.v - plant.v) ** 2))) > 10 * err * float(
        np.sqrt(np.mean(plant.v**2))
    ), "the drift hardly moves this run: the check shows nothing"


def test_a_hot_winding_is_named_and_its_drift_recovered(
    params: VehicleParams, hot: tuple[DrawnTruck, Effects, int]
) -> None:
    truck, eff, log_seed = hot
    d = diagnose_log(drawn_log(truck, eff, log_seed, SECONDS, with_current=True), params)
    names = [f.name for f in d.effects]
    case = f"k={truck.k_scale:.3g} J={truck.j_scale:.3g} {truck.rate_hz:.0f} Hz"
    assert names == ["resistance_drift"], f"{case}: named {names}"
    found = d.effects[0].params
    assert abs(found["resistance_drift"] / eff.resistance_drift - 1.0) < 0.25, (case, found)
    tau = found["winding_time_constant"]
    assert abs(tau / eff.winding_time_constant - 1.0) < 0.25, (case, found)
    assert d.extended.fit_percent > d.baseline.fit_percent + 2.0


@pytest.mark.parametrize(
    "extra",
    [{}, {"input_delay": 0.021, "battery_sag": 0.15, "current_limit": 6.0, "sensor_lag": 0.02}],
)
def test_the_kernels_heated_run_is_where_the_passes_converge(
    hot: tuple[DrawnTruck, Effects, int], extra: dict[str, float], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stretch cut from the hot run (commands before it, its winding already 60 K
    warm): the kernel's one run gives the speed and the current that the passes reach
    converged far below the shipped tolerance (and the passes need many simulations)."""
    truck, eff, log_seed = hot
    eff = dataclasses.replace(eff, **extra)
    rng = np.random.default_rng(log_seed)
    t, u = excitation(rng, int(SECONDS * truck.rate_hz), h=1.0 / truck.rate_hz)
    cut = len(t) // 3
    args = (truck.params, eff, t[cut:], u[cut:], 0.4, t[cut - 8 : cut], u[cut - 8 : cut], 1.0)
    runs: list[int] = []
    counted = freerun.run

    def counting(*a: object, **kw: object) -> object:
        runs.append(1)
        return counted(*a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(fastsim, "run", counting)
    hot_run = simulate_voltage(*args, rise0=60.0)
    assert len(runs) == 1
    monkeypatch.setattr(ckernel, "available", lambda: False)
    monkeypatch.setattr(fastsim, "DRIFT_TOLERANCE", 1e-14)
    passes = simulate_voltage(*args, rise0=60.0)
    assert len(runs) > 6, "the heating hardly couples this run: the check shows nothing"
    v_scale = float(np.max(np.abs(passes.v)))
    i_scale = float(np.max(np.abs(passes.i)))
    assert v_scale > 0.0 and i_scale > 0.0
    assert float(np.max(np.abs(hot_run.v - passes.v))) <= 1e-9 * v_scale
    assert float(np.max(np.abs(hot_run.i - passes.i))) <= 1e-9 * i_scale
