"""Diagnosis of machines far from the configured truck: the configuration is a prior.

Trucks from 0.01x (wheels off the ground) to 100x (a loaded trailer) the default inertia
and 0.1x to 10x the motor constant, always diagnosed against the *default* configuration:
the extended model is never below the data's own least-squares model (WPILib SysId's),
the machine is fitted anyway (its inertia recovered, or the limit that stopped it
reported), and a machine unlike the configured one is named in a note with the numbers.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from labkit.synth import plant_log

from truckd.config.truck import load_config
from truckd.ident.api import diagnose_log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def _draw(seed: int) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    return float(np.exp(rng.uniform(np.log(0.01), np.log(100.0)))), float(
        np.exp(rng.uniform(np.log(0.1), np.log(10.0)))
    )


CASES = [(0.01, 1.0), (100.0, 1.0), (0.01, 0.3), (1.0, 0.1), (1.0, 10.0), _draw(7), _draw(11)]
"""(inertia, motor constant) relative to the default: the ends of the range and draws."""


def _truck(p: VehicleParams, j: float, k: float) -> VehicleParams:
    return p.replace(
        K_v=p.K_v * k,
        K_T=p.K_T * k,
        K_coulomb=p.K_coulomb * k,
        K_stiction=p.K_stiction * k,
        J_S=p.J_S * j,
    )


@pytest.mark.parametrize(("j", "k"), CASES, ids=[f"J{j:.3g}x-K{k:.3g}x" for j, k in CASES])
def test_any_machine_is_fitted_and_never_below_least_squares(j: float, k: float) -> None:
    p = load_config().vehicle
    q = _truck(p, j, k)
    top = p.V_batt / (q.K_v / q.ratio)
    log = plant_log(q, Effects(), seed=3, n=3000, noise_v=0.004 * top, with_current=False)
    d = diagnose_log(log, p)
    ls = d.least_squares
    assert ls is not None and ls["fit_percent"] is not None
    assert d.extended.fit_percent >= ls["fit_percent"]
    assert d.vehicle is not None
    tau = q.J_S * q.R_m / (q.K_T * q.K_v)
    binding = [n for n in d.notes if n.startswith("limit binds: J_S")]
    if 0.05 <= tau <= 3.0:  # a time constant the 30 s log shows
        # Fitted, not boxed: kA (J_S R_m/K_T) within 20 % of the truck's, or the limit
        # that stopped it is reported.
        ka_true = q.J_S * q.R_m / q.K_T
        ka_fit = d.vehicle.J_S * d.vehicle.R_m / d.vehicle.K_T
        assert abs(ka_fit / ka_true - 1.0) < 0.2 or binding
    # A machine unlike the configured one is said so, with the number.
    j_fit = d.vehicle.J_S / p.J_S
    said = [n for n in d.notes if n.startswith("inertia ")]
    if j_fit < 0.1 or j_fit > 10.0:
        assert said and f"{j_fit:.3g}x" in said[0]
    else:
        assert not said


def test_a_limit_that_binds_is_reported_with_the_fit_without_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Seed bounds narrowed to 1.05x around the start and a truck whose inertia the start
    gets 30 % wrong: J_S ends on a limit, and the note gives the fit with it and after a
    refit without it (which cannot be worse)."""
    import truckd.ident.linear as linear
    import truckd.ident.voltage as voltage
    from truckd.ident.linear import Feedforward

    p = load_config().vehicle
    q = _truck(p, 0.5, 1.0)
    log = plant_log(q, Effects(), seed=5, n=3000, with_current=False)
    real = linear.start_model

    def off_start(p0: VehicleParams, runs: object) -> tuple[VehicleParams, Feedforward | None]:
        p_lin, ff = real(p0, runs)  # type: ignore[arg-type]
        return p_lin.replace(J_S=1.3 * p_lin.J_S), ff

    monkeypatch.setattr(voltage, "SEED_ROOM", 1.05)
    # The least-squares stage (linear.least_squares_stage) starts from these.
    monkeypatch.setattr(linear, "start_model", off_start)
    monkeypatch.setattr(linear, "least_squares_model", lambda *a: None)
    d = diagnose_log(log, p)
    notes = [n for n in d.notes if n.startswith("limit binds: J_S")]
    assert notes, d.notes
    assert notes == [n for n in d.alerts if n.startswith("limit binds: J_S")]
    m = re.search(r"fit ([-\d.]+) % with the limit, ([-\d.]+) % without", notes[0])
    assert m is not None, notes[0]
    with_it, without = float(m.group(1)), float(m.group(2))
    assert without >= with_it
