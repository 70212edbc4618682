"""Stage 7 of the diagnosis (:mod:`truckd.ident.diagnose`): the report.

The extended model held against SysId's least-squares model, the limits it ends on,
what the runs cannot determine, and whether its residual leaves structure
(``unexplained``), assembled into the :class:`truckd.ident.result.Diagnosis`.  Pure
numerics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.chatter import chatter_note, spans_json
from truckd.ident.choice import Choice
from truckd.ident.data import (
    Series,
    fit_ceiling_percent,
    merged,
    noise_std,
)
from truckd.ident.linear import (
    Feedforward,
    LeastSquares,
    LinearStart,
)
from truckd.ident.physics import (
    configuration_notes,
    vehicle_problems,
)
from truckd.ident.refit import Refit
from truckd.ident.residuals import Whiteness, looks_like
from truckd.ident.result import CandidateRow, Diagnosis, Finding, ModelSummary, Traces
from truckd.ident.runs import Prepared
from truckd.ident.scoring import Progress, residual_signals, summary, whiteness_of
from truckd.ident.seed import DETERMINED, Seed
from truckd.ident.selection import (
    white,
)
from truckd.ident.trials import Trials
from truckd.ident.voltage import (
    Param,
    fit_with_stiction,
    value_of,
    weights_for,
)
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def _least_squares_json(ls: LeastSquares, fit_pct: float) -> dict[str, float | None]:
    """The ``least_squares`` object of the JSON (reference section 4)."""
    se = ls.se
    out: dict[str, float | None] = {"kS": ls.ff.kS, "kV": ls.ff.kV, "kA": ls.ff.kA}
    for k, e in zip(("kS", "kV", "kA"), se, strict=True):
        out[f"{k}_se"] = float(e) if np.isfinite(e) else None
    out["fit_percent"] = float(fit_pct)
    return out


BOUND_TOL = 1e-3
"""A parameter within this fraction of a limit ends on that limit."""

UNBOUND = 100.0
"""The refit without a binding limit moves it this factor further out."""


def _binding_limits(
    p: VehicleParams,
    e: Effects,
    free: Sequence[Param],
    fit_data: list[Series],
    report: Sequence[Series],
    grid: Sequence[float],
    progress: Progress,
) -> list[str]:
    """One note per free parameter of the final model that ends on a limit of its range
    (zero lower limits excepted: a sign, not a size), with the report fit with the
    limit and after a refit with it moved :data:`UNBOUND` times further out."""
    out = []
    w = weights_for(fit_data)
    for k, f in enumerate(free):
        if f.name == "stiction_excess":
            continue
        val = value_of(p, e, f.name)
        at_lo = f.lo != 0.0 and abs(val - f.lo) <= BOUND_TOL * abs(f.lo)
        at_hi = f.hi != 0.0 and abs(val - f.hi) <= BOUND_TOL * abs(f.hi)
        if not (at_lo or at_hi):
            continue
        bound = f.lo if at_lo else f.hi
        wider = (
            dataclasses.replace(f, lo=f.lo / UNBOUND if f.lo > 0 else f.lo * UNBOUND)
            if at_lo
            else dataclasses.replace(f, hi=f.hi * UNBOUND if f.hi > 0 else f.hi / UNBOUND)
        )
        trial = [*free[:k], wider, *free[k + 1 :]]
        progress(f"{f.name} ends on its limit {bound:.3g}: refit without it")
        refit = fit_with_stiction(p, e, trial, fit_data, w, grid, progress)
        with_pct = summary(p, e, report)[0].fit_percent
        without = summary(refit.params, refit.effects, report)[0].fit_percent
        new_val = value_of(refit.params, refit.effects, f.name)
        out.append(
            f"limit binds: {f.name} = {val:.3g} ends on its {'lower' if at_lo else 'upper'} "
            f"limit {bound:.3g}; fit {with_pct:.1f} % with the limit, {without:.1f} % "
            f"without it ({f.name} = {new_val:.3g})"
        )
    return out


SIGN_CORR = -0.3
"""Speed and voltage correlated below this: one of them has the wrong sign."""
SLOW_STEP_S = 1.0
"""A median time step above this (s) is no motor's log in seconds."""


def _extended_of(refit: Refit, choice: Choice, trials: Trials) -> _Extended:
    """The joint refit's model (its accepted causes not kept switched off), or the seed
    when the refit neither kept a cause nor beat it."""
    off = {trials.by_name[a].param.name: 0.0 for a in choice.accepted if a not in refit.kept}
    final, base = refit.final, refit.base_pol
    return _Extended(
        findings=refit.findings,
        kept=refit.kept,
        summary=refit.ext_sum,
        y=refit.y_ext,
        params=final.params if refit.refitted else base.params,
        effects=dataclasses.replace(final.effects, **off) if refit.refitted else base.effects,
        rows=dict(refit.rows),
    )


def _refit_note(refit: Refit) -> list[str]:
    """The note when the extended model is the seed refitted, without any cause."""
    if not refit.refitted or refit.kept:
        return []
    return [
        "no cause named, but the seed refitted jointly on more of the data fits the report "
        f"data better ({refit.base_sum.fit_percent:.1f} -> {refit.ext_sum.fit_percent:.1f} "
        "%): the extended model is that refit"
    ]


def suspect_columns(runs: Sequence[Series]) -> list[str]:
    """What looks like a column in the wrong sign or unit, said with the numbers (the
    fit goes on: the notes a user must see)."""
    out: list[str] = []
    u = np.concatenate([r.inp for r in runs])
    v = np.concatenate([r.v for r in runs])
    if np.std(u) > 0.0 and np.std(v) > 0.0:
        corr = float(np.corrcoef(u, v)[0, 1])
        if corr < SIGN_CORR:
            out.append(
                f"the speed falls as the voltage rises (correlation {corr:+.2f}): the "
                "encoder or the motor wired the other way round? Flip the sign of v (or "
                "u) in the log; on a truck, plant.wiring or the firmware's encoder sign"
            )
    step = float(np.median(np.concatenate([np.diff(r.t) for r in runs])))
    if step > SLOW_STEP_S:
        out.append(
            f"the median time step is {step:.4g} s: is t in seconds? (a log in "
            "milliseconds reads 1000 times too slow: divide t by 1000)"
        )
    return out


UNIT_ROOM = 20.0
"""A speed or current this many times what the configured truck could reach at the log's
largest command is taken for a unit slip and said: a wheel's rpm reads 225 times its m/s
on the default truck, a wheel's rad/s 24 times, the motor's 650 times, mA 1000 times A;
other machines' shooters and drivetrains on real SysId logs reach 13-15 times."""


def unit_notes(runs: Sequence[Series], p0: VehicleParams, speed: bool = True) -> list[str]:
    """A speed (``speed``: the logs' positions are in m) or a current far beyond what the
    configured truck ``p0`` reaches at the log's largest command, said with the numbers:
    the configuration is a prior, so only a factor of :data:`UNIT_ROOM` and more, where
    a unit slip (not another machine) is the likely cause."""
    out: list[str] = []
    u_top = max(float(np.max(np.abs(r.inp))) for r in runs)
    if not u_top > 0.0:
        return out
    v_top = max(float(np.max(np.abs(r.v))) for r in runs)
    v_free = u_top / p0.K_v * p0.ratio  # the configured truck's no-load speed there
    if speed and v_top > UNIT_ROOM * v_free:
        out.append(
            f"the speed reaches {v_top:.4g} m/s, {v_top / v_free:.0f}x the configured truck's "
            f"no-load speed at {u_top:.3g} V ({v_free:.3g} m/s): is v in m/s (not rpm or "
            "rad/s)?"
        )
    i_top = max((float(np.max(np.abs(r.i))) for r in runs if r.i is not None), default=0.0)
    i_stall = u_top / p0.R_m  # the configured motor's stall current there
    if i_top > UNIT_ROOM * i_stall:
        out.append(
            f"the current reaches {i_top:.4g} A, {i_top / i_stall:.0f}x the configured "
            f"motor's stall current at {u_top:.3g} V ({i_stall:.3g} A): is i in A (not mA)?"
        )
    return out


def _notes(
    runs: Sequence[Series],
    ff: Feedforward | None,
    fisher: tuple[float, float, float] | None = None,
) -> list[str]:
    """What these runs can and cannot determine."""
    whole = merged(runs)
    notes = [
        "L_m is not identifiable from speed sampled far slower than L_m/R_m (< 1 ms): "
        "kept at the configured value",
        "K_T is not identifiable without a known torque: held at the configured K_T/K_v "
        "ratio (J_S, K_coulomb, K_stiction are determined relative to it)",
        "n_g, n_fd, r_w and m are not identifiable from voltage and speed: kept as configured",
    ]
    if whole.i is None:
        notes.append(
            "no current column: R_m held at the configured value (only J_S R_m/K_T, "
            "K_coulomb R_m/K_T, K_stiction R_m/K_T and K_v are determined); viscous_friction "
            "is not a candidate (indistinguishable from K_v without current)"
        )
    else:
        notes.append("current column used: R_m and K_v determined from the electrical balance")
    if ff is None:
        notes.append(
            "too few samples in motion for the linear estimate: the fit started from the "
            "configuration"
        )
    else:
        names = {"kS": "K_coulomb", "kV": "K_v", "kA": "J_S"}
        # Determined: both the linear estimate and the simulation-error fit pin it down
        # (the windowed OLS alone called kA determined from slow symmetric ramps).
        rel = ff.rel_se if fisher is None else tuple(map(max, ff.rel_se, fisher))
        good = [k for k, e in zip(("kS", "kV", "kA"), rel, strict=True) if e < DETERMINED]
        bad = [k for k in ("kS", "kV", "kA") if k not in good]
        if good:
            notes.append(
                "determined by these runs: " + ", ".join(f"{k} ({names[k]})" for k in good)
            )
        if bad:
            notes.append(
                "poorly determined by these runs (relative standard error above "
                f"{DETERMINED:.0%}): "
                + ", ".join(f"{k} ({names[k]})" for k in bad)
                + " (a slow ramp hardly shows kA, a single step barely separates kS from kV)"
            )
    starts = sum(
        1
        for r in runs
        if np.any((np.abs(r.v[:-1]) < 1e-3 + 3 * noise_std(r.v)) & (np.abs(r.inp[:-1]) > 0))
    )
    if not starts:
        notes.append("no start from rest: K_stiction (breakaway) kept near its configured value")
    if not np.any(whole.inp < 0) or not np.any(whole.v < 0):
        notes.append("motion in one direction only: friction asymmetry cannot be checked")
    return notes


def report_stage(
    prep: Prepared,
    start: LinearStart,
    seed: Seed,
    trials: Trials,
    choice: Choice,
    refit: Refit,
    progress: Progress,
) -> Diagnosis:
    """Stage 7 of the diagnosis: the extended model held against the least-squares
    model, the limits it ends on, what the runs cannot determine, and whether its
    residual leaves structure (``unexplained``)."""
    by_name = trials.by_name
    ext = _extended_of(refit, choice, trials)
    notes = _notes(prep.runs, start.ff, seed.fisher)
    ls_json: dict[str, float | None] | None = None
    below = None
    if start.ls is not None:
        ext, ls_json, below = _against_least_squares(ext, start.ls, prep.report, progress)
    notes.extend([below] if below is not None else _refit_note(refit))  # the model it is
    findings, kept, ext_sum, y_ext = ext.findings, ext.kept, ext.summary, ext.y
    ext_params, ext_effects, rows = ext.params, ext.effects, ext.rows
    free = [*seed.free, *[x for a in kept for x in (by_name[a].param, *by_name[a].extra)]]
    binding = _binding_limits(
        ext_params, ext_effects, free, prep.polish_data, prep.report, seed.grid, progress
    )
    notes.extend(binding)
    machine = [*suspect_columns(prep.runs), *configuration_notes(ext_params, prep.p0)]
    notes.extend(machine)
    alerts = [n for n in notes if n.startswith(("the simulation-error fit", "no cause named, but"))]
    alerts.extend([*binding, *machine])
    notes.extend(vehicle_problems(ext_params, prep.runs))
    residual = np.concatenate([r.v for r in prep.report]) - y_ext
    wt, unexplained, at_noise = whiteness_of(residual, prep.report)
    looks = looks_like(residual, residual_signals(prep.report))
    del residual
    if unexplained:
        line = _unexplained_line(wt, looks)
        notes.append(line)
        alerts.append(line)
    chatter, fit_with = _chatter(prep, ext)
    notes.extend(chatter)
    alerts.extend(chatter)
    if prep.supply_note is not None:
        notes.insert(0, prep.supply_note)
    notes[:0] = prep.spike_notes
    alerts[:0] = prep.spike_notes
    rep = merged(prep.report)
    return Diagnosis(
        input="voltage",
        samples=sum(len(r) for r in prep.runs),
        baseline=refit.base_sum,
        effects=findings,
        extended=ext_sum,
        unexplained=unexplained,
        ambiguous=choice.ambiguous,
        candidates=[rows[c.name] for c in trials.cands],
        notes=notes,
        traces=Traces(
            t=rep.t, inp=rep.inp, y=rep.v, y_base=refit.y_base, y_ext=y_ext, i=rep.i, x=rep.x
        ),
        vehicle=ext_params,
        model_effects=ext_effects,
        residual_stats=_residual_stats(wt, looks),
        # A cause impossible on top of some others but accepted in the end is no rejection.
        rejected=[r for r in trials.judge.rejected if r.name not in {f.name for f in findings}],
        linear=None if start.ff is None else start.ff.to_json(),
        least_squares=ls_json,
        alerts=alerts,
        runs=len(prep.runs),
        explains=not unexplained and white(wt) and at_noise,
        # the extended model is at least the least squares (_against_least_squares)
        fit_ceiling=fit_ceiling_percent(
            prep.report, max(refit.base_sum.fit_percent, ext_sum.fit_percent)
        ),
        chatter=[*spans_json(prep.chatter, "log"), *spans_json(prep.chatter_val, "validation")],
        fit_with_chatter=fit_with,
    )


def _chatter(prep: Prepared, ext: _Extended) -> tuple[list[str], float | None]:
    """The note on the chatter left out (none: no note) and the extended model's fit
    (%) on the report data with it left in (None: there was none)."""
    if not (prep.chatter or prep.chatter_val):
        return [], None
    with_it = summary(ext.params, ext.effects, prep.uncut_report)[0].fit_percent
    note = chatter_note(prep.chatter, prep.chatter_val, ext.summary.fit_percent, with_it)
    return [note], with_it


def _unexplained_line(wt: Whiteness, looks: dict[str, float]) -> str:
    """The note that the residual keeps structure, and what it correlates with."""
    what = (
        ", ".join(f"{k} (r = {c:+.2f})" for k, c in looks.items())
        if looks
        else "none of speed, acceleration, the command's sign, time or position"
    )
    return (
        f"unexplained: the best model leaves structure in the residual (autocorrelation "
        f"{wt.acf_outside:.0%} and cross-correlation with the input {wt.ccf_outside:.0%} "
        f"of lags outside the band, RMS {wt.rms:.3g} against noise {wt.noise:.3g} m/s); "
        f"it correlates with {what}"
    )


@dataclass(frozen=True)
class _Extended:
    """The extended model as the report states it."""

    findings: list[Finding]
    kept: list[str]
    summary: ModelSummary
    y: np.ndarray
    params: VehicleParams
    effects: Effects
    rows: dict[str, CandidateRow]


def _against_least_squares(
    ext: _Extended, ls: LeastSquares, report: Sequence[Series], progress: Progress
) -> tuple[_Extended, dict[str, float | None], str | None]:
    """The extended model, or SysId's least-squares model when that fits the report
    data better (then with a note saying so); and the ``least_squares`` JSON object."""
    ls_sum, y_ls = summary(ls.params, Effects(), report)
    ls_json = _least_squares_json(ls, ls_sum.fit_percent)
    progress(f"least squares (SysId's model): fit {ls_sum.fit_percent:.2f} %")
    if not ext.summary.fit_percent < ls_sum.fit_percent:
        return ext, ls_json, None
    note = (
        f"the simulation-error fit ({ext.summary.fit_percent:.1f} %) does not beat the "
        f"data's own least-squares model ({ls_sum.fit_percent:.1f} %) on the "
        "validation data: the extended model is the least-squares model"
    )
    rows = dict(ext.rows)
    for name in ext.kept:
        rows[name] = dataclasses.replace(
            rows[name], accepted=False, note="below least squares: not accepted"
        )
    below = _Extended([], [], ls_sum, y_ls, ls.params, Effects(), rows)
    return below, ls_json, note


def _residual_stats(wt: Whiteness, looks: dict[str, float]) -> dict[str, float]:
    """The ``residual_stats`` of the diagnosis: whiteness and correlations."""
    return {
        "rms": wt.rms,
        "noise": wt.noise,
        "structure": wt.structure,
        "acf_outside_fraction": wt.acf_outside,
        "ccf_outside_fraction": wt.ccf_outside,
        **{f"corr_{k}": c for k, c in looks.items()},
    }
