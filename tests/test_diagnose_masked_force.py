"""A constant load force on a drawn truck with a long dead time: the delay is the only
cause that passes alone and masks the force in the single trials; the selection's extra
rounds, started by the structure the ramps and steps keep (not only the validation
chirp's), name it."""

from __future__ import annotations

import random

from truckd.cli import platoon_diagnosis as pd
from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.model.params import VehicleParams
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon_scenarios import ACTUATION_DELAY_S
from truckd.sim.platoon_truck import draw_platoon_truck, with_delay

FORCE_TOL = 0.02
"""Largest relative error of the named load force in volts, the voltage that holds it at
the motor (``force_to_torque(F) R_m / K_T``: what a voltage log determines; measured
0.07 %).  In newtons it is 1.19 N for 1.34 N: the model keeps the configured ``R_m``
(0.0847 ohm against the drawn 0.0749 ohm), which a log without current does not show."""


def _volts(p: VehicleParams, force: float) -> float:
    """The armature voltage (V) that holds ``force`` (N) on the truck ``p`` at rest."""
    return p.force_to_torque(force) * p.R_m / p.K_T


def test_drawn_truck_identification_names_its_load_force() -> None:
    """The ninth truck ``truckd sim --platoon 10 --mixed --seed 1`` draws (1.34 N load
    force, twice the configured mass) with the platoon scenarios' 0.15 s dead time: its
    identification drive's diagnosis names the force, within :data:`FORCE_TOL` in volts,
    and the dead time."""
    cfg = load_config()
    setup = SimSetup(
        cfg.vehicle, cfg.plant, cfg.control, ControlModel(cfg.vehicle), ticks_per_rev=512
    )
    rng = random.Random(1)
    truth = with_delay([draw_platoon_truck(setup, rng) for _ in range(9)][-1], ACTUATION_DELAY_S)
    force = truth.plant_config.effects.load_force
    assert force > 1.0  # the draw this test is about

    model = pd.identify_truck(cfg, truth)

    named = _volts(model.vehicle, model.effects.load_force)
    true = _volts(truth.plant_params, force)
    assert abs(named - true) <= FORCE_TOL * true
    assert abs(model.effects.input_delay - ACTUATION_DELAY_S) < 0.02
