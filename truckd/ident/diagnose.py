"""Diagnosis of a voltage-input log: a pipeline of seven stages, each a module with plain
inputs and outputs, called once, in order.

1. **Read runs** (:mod:`truckd.ident.runs`): the supply checked, positions added,
   estimation and validation runs chosen (the log's first 70 % when no validation log
   is given), and the samples each later fit uses.
2. **Least squares** (:func:`truckd.ident.linear.least_squares_stage`): SysId's linear
   estimate (the seed fit's start) and its least-squares model (the bar to clear).
3. **Seed fit** (:mod:`truckd.ident.seed`): motor, inertia, Coulomb and stiction by
   simulation error on the estimation data.
4. **Candidates** (:mod:`truckd.ident.trials`): each candidate effect alone on top of
   the seed (grid start, joint refit, :mod:`truckd.ident.extend`).
5. **Selection** (:mod:`truckd.ident.choice`): a candidate earns its place when it
   lowers the information criterion on the estimation data (``delta BIC < -BIC_MIN``)
   *and* the validation cost by at least ``REL_MIN`` (:mod:`truckd.ident.judge`).
   They are accepted greedily, strongest first, each refitted jointly with those
   already accepted; a candidate that passed alone but adds nothing once a rival is
   in, while having explained about as much alone, is reported as ``ambiguous``.
6. **Joint refit** (:mod:`truckd.ident.refit`): the extended model on more of the
   data; each accepted cause kept only when it raises the report fit.
7. **Report** (:mod:`truckd.ident.verdict`): the residual of the extended model on
   the report data decides ``unexplained``: it is not white (autocorrelation beyond the
   99 % band at many lags) and its RMS clearly exceeds the measurement noise.

Every stage simulates through :mod:`truckd.ident.voltage` (the fitting engine) and
scores through :mod:`truckd.ident.scoring`.
"""

from __future__ import annotations

from collections.abc import Sequence

from truckd.ident import fastsim
from truckd.ident.chatter import chatter_where, without_chatter
from truckd.ident.choice import selection_stage
from truckd.ident.data import Series, chunks_of_runs, despiked_runs, merged
from truckd.ident.fanout import Mapper, in_order
from truckd.ident.linear import least_squares_model, least_squares_stage, linear_start
from truckd.ident.refit import refit_stage
from truckd.ident.result import Diagnosis
from truckd.ident.runs import FIT_BUDGET, budget, prepare, supply_for
from truckd.ident.scoring import Progress, quiet
from truckd.ident.seed import fit_seed, seed_stage
from truckd.ident.trials import candidates_stage
from truckd.ident.verdict import report_stage
from truckd.ident.voltage import FitResult, restick, seed_params, stiction_grid, weights_for
from truckd.model.params import VehicleParams


def diagnose_voltage(
    p0: VehicleParams,
    runs: Sequence[Series],
    validate: Sequence[Series] | None = None,
    progress: Progress = quiet,
    mapper: Mapper = in_order,
) -> Diagnosis:
    """Diagnose voltage-input runs (see module docstring); ``validate`` runs when given.
    The supply is raised to the largest command when the configured one is lower
    (:func:`truckd.ident.runs.supply_for`, noted).  ``mapper`` runs the fits of stages 4
    and 5 that do not depend on each other (:mod:`truckd.ident.fanout`; the result is
    the same whichever runs them)."""
    prep = prepare(p0, runs, validate, progress)
    start = least_squares_stage(prep.p0, prep.est, progress)
    seed = seed_stage(prep, start, progress, mapper)
    trials = candidates_stage(prep, seed, progress, mapper)
    choice = selection_stage(prep, seed, trials, progress, mapper)
    refit = refit_stage(prep, seed, trials, choice, progress)
    fastsim.forget()  # the fits' caches: the report simulates the report's runs
    return report_stage(prep, start, seed, trials, choice, refit, progress)


def identify_voltage(
    p0: VehicleParams, runs: Sequence[Series], progress: Progress = quiet
) -> FitResult:
    """Seed model fitted to all runs of voltage-input logs (no effects); the supply raised
    to the largest command when the configured one is lower (:func:`supply_for`); the
    speed's chatter left out (:func:`truckd.ident.chatter.without_chatter`)."""
    p0, supply_note = supply_for(p0, runs)
    if supply_note is not None:
        progress(supply_note)
    runs, spikes = despiked_runs(runs, "the data")
    if spikes is not None:
        progress(spikes)
    runs, chatter = without_chatter(runs)
    if chatter:
        progress(f"chatter left out: {chatter_where(chatter)}")
    whole = merged(runs)
    fit_data = chunks_of_runs(runs, budget(runs, FIT_BUDGET))
    w = weights_for(fit_data)
    p_lin, _ = linear_start(p0, runs, progress)
    free = seed_params(p_lin, whole.i is not None)
    grid = stiction_grid(p0, whole)
    ls = least_squares_model(p0, runs)
    best = fit_seed(p0, p_lin, free, fit_data, w, grid, progress, ls)
    return restick(best, grid, list(runs), w)
