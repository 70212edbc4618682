"""A cause's place in the model: the points of fit it gains where it acts, or a fifth of
the validation cost it removes (:meth:`truckd.ident.judge.Judge.earns`)."""

from __future__ import annotations

import numpy as np
from labkit.synth import plant_log

from truckd.ident.candidates import voltage_candidates
from truckd.ident.data import runs_from_logs
from truckd.ident.judge import STRONG_REL, Judge, hill_support
from truckd.ident.runs import prepare
from truckd.ident.scoring import GAIN_MIN, Model, gain_where_acting, quiet, val_cost
from truckd.ident.voltage import FitResult, Weights, residuals
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def test_a_low_speed_friction_earns_its_place_by_the_cost_it_removes(
    params: VehicleParams,
) -> None:
    """A Stribeck friction 0.006 N m above Coulomb in the default truck's log (it costs
    the controller 4.7 mm of gap error in stop-and-go): the true model with it removes
    over a fifth of the validation cost of the true model without it, but gains under
    half a point of fit where it acts (the speed spreads widely there): the cost alone
    earns it its place.  A model that removes less does not."""
    eff = Effects(stribeck=0.006, stribeck_speed=0.1)
    runs = runs_from_logs([plant_log(params, eff, seed=2026, n=3000)], None)
    prep = prepare(params, runs, None, quiet)
    judge = Judge(prep, {c.name: c for c in voltage_candidates(params, prep.whole)})

    def model(e: Effects, names: tuple[str, ...]) -> Model:
        f = FitResult(params, e, 0.0, 0, 0)
        return Model(f, names, val_cost(f, prep.val_data, prep.w))

    with_it, without = model(eff, ("stribeck",)), model(Effects(), ())
    assert with_it.val_cost < (1.0 - STRONG_REL) * without.val_cost
    gain = gain_where_acting(with_it.fit, without.fit, prep.val, judge.noise_val)
    assert 0.0 < gain < GAIN_MIN
    assert judge.earns("stribeck", with_it, without)
    # The same model judged against one it improves by less than a fifth: points decide.
    close = Model(without.fit, (), with_it.val_cost / (1.0 - 0.5 * STRONG_REL))
    assert not judge.earns("stribeck", with_it, close)


def test_a_hills_support_masks_the_residuals_of_a_held_speed(params: VehicleParams) -> None:
    """A speed that updates every 4th sample (sample and hold, as some real logs have):
    the hill's support has one entry per residual, with current and without; counting
    every sample instead made the hill check index past the residuals."""
    log = plant_log(params, Effects(), seed=7, n=800)
    v = log["v"]
    held = Log({**log.columns, "v": np.repeat(v[::4], 4)[: len(v)]}, "<held speed>")
    runs = runs_from_logs([held], None)
    hill = Effects(load_force=0.5, hill_start=0.1, hill_length=0.5)
    for w in (Weights(v=100.0), Weights(v=100.0, i=10.0)):
        res = residuals(params, Effects(), runs, w)
        mask = hill_support(params, hill, runs, w)
        assert mask.shape == res.shape
        assert len(res) < sum(len(s) for s in runs) * (2 if w.i else 1)  # held: fewer
