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
