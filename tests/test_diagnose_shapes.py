"""Logs shaped as people record them, beyond the random excitation of the other tests: a
single step, and a truck on a larger battery than the configured one."""

from __future__ import annotations

import numpy as np
import pytest

from truckd.ident.api import diagnose_log, identify_log
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop


def _log(p: VehicleParams, t: np.ndarray, u: np.ndarray, seed: int) -> Log:
    sim = simulate_open_loop(p, t, u, PlantConfig(effects=Effects(), noise_v=0.01, seed=seed))
    return Log({"t": t, "u": u, "v": sim.v}, f"<step seed {seed}>")


@pytest.mark.parametrize("levels", [(0.0, 4.0), (0.0, -5.0), (3.0, 6.0)])
def test_a_step_log_is_diagnosed(params: VehicleParams, levels: tuple[float, float]) -> None:
    """One or two command levels leave a dead zone nothing to lie between: the candidate
    is not tried (it crashed the diagnosis: an empty start grid)."""
    t = np.arange(0.0, 8.0, 0.01)
    u = np.where(t < 1.0, levels[0], levels[1])
    d = diagnose_log(_log(params, t, u, 5), params)
    assert d.baseline.fit_percent > 90.0
    assert d.effects == []
    assert all(c.name != "dead_zone" for c in d.candidates)


def test_commands_above_the_configured_supply_are_not_clipped(params: VehicleParams) -> None:
    """A truck on a 12 V battery, commanded up to 11 V, diagnosed with the configured
    7.2 V: the supply is raised to the commands and noted, nothing is named (before: the
    simulation clipped every command above 7.2 V, and a dead-zone offset and a K_v 20 %
    low explained the clipping)."""
    truck = params.replace(V_batt=12.0)
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 40.0, 0.01)
    u = np.repeat(rng.uniform(-11.0, 11.0, 40), 100)
    u[np.abs(u) < 1.0] = 0.0
    log = _log(truck, t, u, 9)
    d = diagnose_log(log, params)
    assert d.effects == []
    assert any("supply" in n and "V_batt" in n for n in d.notes)
    assert d.extended.fit_percent > 98.0
    assert d.extended.params["K_v"] == pytest.approx(truck.K_v, rel=0.03)
    model = identify_log(log, params).vehicle
    assert model.V_batt == pytest.approx(float(np.max(np.abs(u))))
    assert model.K_v == pytest.approx(truck.K_v, rel=0.03)


def _levels(rng: np.random.Generator, seconds: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Random command levels in [-7, 7] V (some 0) held 0.3-2 s, sampled every h."""
    n = int(seconds / h)
    t = np.arange(n) * h
    u = np.zeros(n)
    k = 0
    while k < n:
        length = int(rng.uniform(0.3, 2.0) / h)
        u[k : k + length] = 0.0 if rng.random() < 0.15 else rng.uniform(-7.0, 7.0)
        k += length
    return t, u


def _drawn(p: VehicleParams, effects: Effects, seconds: float, h: float, seed: int) -> Log:
    t, u = _levels(np.random.default_rng(seed), seconds, h)
    cfg = PlantConfig(effects=effects, noise_v=0.01, seed=seed)
    return Log({"t": t, "u": u, "v": simulate_open_loop(p, t, u, cfg).v}, f"<seed {seed}>")


def test_a_stiction_far_from_the_configured_one_is_found(params: VehicleParams) -> None:
    """Breakaway three times the configured one: the seed fit started from the configured
    stiction, moved Coulomb friction and K_v to absorb it (K_coulomb 0.026 for 0.015) and
    stayed there; a start with the breakaway scanned first finds both frictions."""
    truck = params.replace(K_stiction=0.07)
    model = identify_log(_drawn(truck, Effects(), 60.0, 0.01, 15), params).vehicle
    assert model.K_coulomb == pytest.approx(truck.K_coulomb, rel=0.05)
    assert model.K_stiction == pytest.approx(truck.K_stiction, rel=0.15)
    assert model.K_v == pytest.approx(truck.K_v, rel=0.02)


def test_a_drag_stronger_than_the_friction_is_found(params: VehicleParams) -> None:
    """A fast truck (gear ratio 5) with a drag of 0.6 N s^2/m^2, 20 times its friction at
    top speed: the drag's bound was 50 times the Coulomb force there (0.16 came out, with
    a false saturation and load beside it); now what takes the whole stall force."""
    truck = params.replace(n_g=5.0)
    d = diagnose_log(_drawn(truck, Effects(aero_drag=0.6), 60.0, 0.01, 18), truck)
    assert [e.name for e in d.effects] == ["aero_drag"]
    assert d.effects[0].params["aero_drag"] == pytest.approx(0.6, rel=0.05)


def test_a_sensor_lag_in_a_1khz_log_is_found(params: VehicleParams) -> None:
    """At 1 kHz the fixed sample budgets made 1 s chunks, shorter than the truck's
    response: the lag was taken for inertia (J_S a third, a false battery sag).  The
    budgets now hold the same time as at 100 Hz (up to five times the samples)."""
    d = diagnose_log(_drawn(params, Effects(sensor_lag=0.1), 20.0, 0.001, 21), params)
    assert [e.name for e in d.effects] == ["sensor_lag"]
    assert d.effects[0].params["sensor_lag"] == pytest.approx(0.1, rel=0.05)


def test_a_force_offset_under_viscous_friction_is_found(params: VehicleParams) -> None:
    """A position-controlled stage (force input, as EMPS): viscous friction 20 N s/m,
    Coulomb 2 N and an offset of 1.5 N that does not pass on its own.  Only candidates
    that passed alone competed after the first round: the offset went unnamed and Coulomb
    friction came out 1.45 N; every candidate now competes in every round."""
    rng = np.random.default_rng(81)
    mass, f_c, f_v, off = 5.0, 2.0, 20.0, 1.5
    h, sub = 0.005, 20
    n = int(40.0 / h)
    target = np.zeros(n)
    k = 0
    while k < n:
        length = int(rng.uniform(0.5, 2.0) / h)
        target[k : k + length] = rng.uniform(-0.3, 0.3)
        k += length
    x = v = 0.0
    xs, fs = np.zeros(n), np.zeros(n)
    for j in range(n):
        f = 400.0 * (target[j] - x) - 60.0 * v + rng.normal(0.0, 0.5)
        fs[j], xs[j] = f, x
        for _ in range(sub):
            a = (f - f_c * np.tanh(v / 0.002) - f_v * v - off) / mass
            v += a * h / sub
            x += v * h / sub
    log = Log({"t": np.arange(n) * h, "F": fs, "x": np.round(xs / 1e-5) * 1e-5}, "<stage>")
    d = diagnose_log(log, params)
    found = {e.name: e.params for e in d.effects}
    assert set(found) == {"viscous_friction", "load_force"}
    assert next(iter(found["load_force"].values())) == pytest.approx(off, rel=0.05)
    assert next(iter(found["viscous_friction"].values())) == pytest.approx(f_v, rel=0.05)
