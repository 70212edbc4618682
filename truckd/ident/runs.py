"""Stage 1 of the diagnosis (:mod:`truckd.ident.diagnose`): the runs as the fit sees them.

The supply raised to the largest command, positions integrated, estimation and
validation runs chosen, and the samples the fitting loop, the selection and the final
refit use (chunks within a budget of samples).  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.chatter import ChatterSpan, without_chatter
from truckd.ident.data import (
    Series,
    chunks_of_runs,
    despiked_runs,
    merged,
    split_runs_for_validation,
    with_position,
)
from truckd.ident.scoring import Progress
from truckd.ident.voltage import (
    Weights,
    weights_for,
)
from truckd.model.params import VehicleParams

FIT_BUDGET = 4000
"""Samples of the estimation data used in the fitting loop (spread over chunks): at
least, and at least 40 s of it (a faster log gets more samples, up to five times: at
1 kHz 4000 samples were 1 s chunks, shorter than a slow truck's response, and the fit
took a sensor lag for inertia)."""

FINAL_BUDGET = 8000
"""Samples used by the final joint refit of the extended model (at least 80 s, as above)."""

VAL_BUDGET = 12000
"""Samples of the validation data used to select candidates (at least 120 s, as above)."""

BUDGET_RATE_HZ = 100.0
"""The sample rate the budgets above are counted at: a faster log gets the same time."""

BUDGET_MAX_FACTOR = 5
"""A faster log's budgets grow at most this much (run time grows with them)."""


def budget(runs: Sequence[Series], samples: int) -> int:
    """``samples`` at :data:`BUDGET_RATE_HZ`, as samples of ``runs`` at their rate."""
    steps = [float(np.median(np.diff(r.t))) for r in runs if len(r) > 1]
    h = float(np.median(steps)) if steps else 1.0 / BUDGET_RATE_HZ
    if not h > 0.0:
        return samples
    per_time = round(samples / (BUDGET_RATE_HZ * h))
    return int(min(max(samples, per_time), BUDGET_MAX_FACTOR * samples))


def supply_for(p0: VehicleParams, runs: Sequence[Series]) -> tuple[VehicleParams, str | None]:
    """The configured truck with its supply ``V_batt`` raised to the largest command the
    runs hold (V), and a note saying so (None when it was high enough).  The driver cannot
    apply more than its supply, so a simulation on the configured one would clip every
    command above it and the fit would explain the clipping by wrong parameters and
    effects (a log recorded on a larger battery)."""
    u_top = max((float(np.max(np.abs(r.inp))) for r in runs if len(r)), default=0.0)
    if not u_top > p0.V_batt * (1.0 + 1e-9):
        return p0, None
    note = (
        f"commands reach {u_top:.4g} V, above the configured supply V_batt = "
        f"{p0.V_batt:.4g} V: the supply is taken as {u_top:.4g} V (set vehicle.V_batt "
        "to the truck's battery voltage)"
    )
    return p0.replace(V_batt=u_top), note


@dataclass(frozen=True)
class Prepared:
    """The runs of one diagnosis as the later stages use them."""

    p0: VehicleParams
    """The configured truck, its supply raised to the largest command (:func:`supply_for`)."""
    supply_note: str | None
    """What :func:`supply_for` says about the supply (None: it was high enough)."""
    spike_notes: list[str]
    """The isolated speed spikes replaced (:func:`truckd.ident.data.despiked_runs`)."""
    runs: list[Series]
    """The runs to diagnose, with positions."""
    validate: list[Series] | None
    """The validation runs given (with positions), None when none were."""
    est: list[Series]
    """Estimation runs: ``runs``, or their first 70 % without validation runs."""
    val: list[Series]
    """Validation runs: ``validate``, or the rest of ``runs``."""
    report: list[Series]
    """The runs the figures are reported on: ``validate`` when given, else ``runs``."""
    whole: Series
    """``runs`` end to end."""
    fit_data: list[Series]
    """Chunks of ``est`` within :data:`FIT_BUDGET`: the fitting loop's data."""
    val_data: list[Series]
    """Chunks of ``val`` within :data:`VAL_BUDGET`: the selection's data."""
    w: Weights
    """Weights of the speed and current residuals on ``fit_data``."""
    fit_runs: list[Series]
    """The runs of the final joint refit (selection done: all the estimation data)."""
    polish_data: list[Series]
    """Chunks of ``fit_runs`` within :data:`FINAL_BUDGET`: the final joint refit's data."""
    chatter: list[ChatterSpan]
    """The stretches of chatter cut out of the runs (:mod:`truckd.ident.chatter`)."""
    chatter_val: list[ChatterSpan]
    """... and out of the validation runs given."""
    uncut_report: list[Series]
    """``report`` with its chatter left in."""


def prepare(
    p0: VehicleParams,
    runs: Sequence[Series],
    validate: Sequence[Series] | None,
    progress: Progress,
) -> Prepared:
    """Stage 1: the supply checked, positions added, estimation and validation chosen,
    and the samples of the fitting loop, the selection and the final refit."""
    p0, supply_note = supply_for(p0, [*runs, *(validate or [])])
    if supply_note is not None:
        progress(supply_note)
    runs, spikes = despiked_runs(runs, "the estimation data" if validate else "the data")
    spike_notes = [spikes] if spikes else []
    if validate:
        validate, spikes_val = despiked_runs(validate, "the validation data")
        spike_notes += [spikes_val] if spikes_val else []
    for note in spike_notes:
        progress(note)
    runs = [with_position(r) for r in runs]
    validate = [with_position(r) for r in validate] if validate else None
    uncut_report = list(validate) if validate else list(runs)
    runs, chatter = without_chatter(runs)
    chatter_val: list[ChatterSpan] = []
    if validate:
        validate, chatter_val = without_chatter(validate)
    if chatter or chatter_val:
        progress(
            f"chatter left out: {sum(s.end - s.start for s in [*chatter, *chatter_val]):.2f} s "
            "of speed swinging fast at a steady command"
        )
    if validate:
        est, val = list(runs), list(validate)
    else:
        est, val = split_runs_for_validation(runs)
    fit_data = chunks_of_runs(est, budget(est, FIT_BUDGET))
    fit_runs = est if validate else list(runs)
    return Prepared(
        p0=p0,
        supply_note=supply_note,
        spike_notes=spike_notes,
        runs=runs,
        validate=validate,
        est=est,
        val=val,
        report=list(validate) if validate else list(runs),
        chatter=chatter,
        chatter_val=chatter_val,
        uncut_report=uncut_report,
        whole=merged(runs),
        fit_data=fit_data,
        val_data=chunks_of_runs(val, budget(val, VAL_BUDGET)),
        w=weights_for(fit_data),
        fit_runs=fit_runs,
        polish_data=chunks_of_runs(fit_runs, budget(fit_runs, FINAL_BUDGET), pieces=8),
    )
