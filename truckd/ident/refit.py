"""Stage 6 of the diagnosis (:mod:`truckd.ident.diagnose`): the joint refit.

The selected model refitted jointly on more of the data, and each accepted cause kept
only when it raises the fit on the report data.  Pure numerics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.candidates import (
    Candidate,
)
from truckd.ident.choice import Choice
from truckd.ident.data import (
    Series,
)
from truckd.ident.extend import params_of, profile_of
from truckd.ident.physics import (
    effects_problems,
)
from truckd.ident.result import (
    CandidateRow,
    Finding,
    ModelSummary,
)
from truckd.ident.runs import Prepared
from truckd.ident.scoring import Progress, summary
from truckd.ident.seed import Seed
from truckd.ident.trials import Trials
from truckd.ident.voltage import (
    FitResult,
    fit_with_stiction,
    restick,
    weights_for,
)

ACTS_MIN = 2e-3
"""A cause whose switching on moves the simulated speed on the report data by less
than this share of the speed's spread (RMS over std) acts on nothing (the residual
floor of :func:`truckd.ident.scoring.whiteness_of`)."""

FINAL_NFEV = 80
"""Evaluations of the final joint refit (R_m and battery sag correlate: they need room)."""


@dataclass(frozen=True)
class Refit:
    """What the joint-refit stage hands on."""

    final: FitResult
    """The extended model fitted jointly on more of the data (or the selection's)."""
    base_pol: FitResult
    """The seed with its stiction re-scanned on all the fit runs."""
    base_sum: ModelSummary
    y_base: np.ndarray
    """The seed's figures and free-run speed on the report runs."""
    findings: list[Finding]
    """The causes kept, each with the report fit it adds."""
    kept: list[str]
    """The accepted candidates that raise the report fit, in order."""
    ext_sum: ModelSummary
    y_ext: np.ndarray
    """The extended model's figures and free-run speed on the report runs."""
    rows: dict[str, CandidateRow]
    refitted: bool = False
    """The extended model is ``final`` (its accepted causes not kept switched off), not
    the seed: a cause was kept, or the refit's parameters beat the seed's without one."""


def refit_stage(
    prep: Prepared, seed: Seed, trials: Trials, choice: Choice, progress: Progress
) -> Refit:
    """Stage 6 of the diagnosis: the final joint refit of the extended model on more of
    the data, then each accepted cause kept only when it raises the report fit.

    Stiction shows only at the breakaways, which chunks may miss: a last look at it on
    all the data.  The final joint refit never drops a cause that earned its place in
    the selection's model: when it would, the selection's model stays.
    """
    grid, accepted, current = seed.grid, choice.accepted, choice.current
    by_name, rows = trials.by_name, dict(choice.rows)
    base_pol = restick(seed.fit, grid, prep.fit_runs, prep.w)
    final = base_pol
    if accepted:
        progress("final joint refit on more data")
        extra = [by_name[a].param for a in accepted if by_name[a].smooth]
        final = fit_with_stiction(
            current.fit.params,
            current.fit.effects,
            [*seed.free, *extra],
            prep.polish_data,
            weights_for(prep.polish_data),
            grid,
            progress,
            max_nfev=FINAL_NFEV,
        )
        final = restick(final, grid, prep.fit_runs, prep.w)
        if effects_problems(final.effects, final.params, prep.runs, prep.p0):
            final = restick(current.fit, grid, prep.fit_runs, prep.w)  # it left the limits
    base_sum, y_base = summary(base_pol.params, base_pol.effects, prep.report)

    def keep(model: FitResult) -> _Kept:
        return _keep(model, accepted, by_name, prep.report, base_sum, y_base)

    # Never worse: each accepted cause must raise the report fit; one that does not is
    # switched off (a cause that lowers the validation fit is no cause).
    findings, kept, ext_sum, y_ext = keep(final)
    if accepted and final is not current.fit:
        sel = restick(current.fit, grid, prep.fit_runs, prep.w)
        alt = keep(sel)
        if len(alt[1]) > len(kept) or (
            len(alt[1]) == len(kept) and alt[2].fit_percent > ext_sum.fit_percent
        ):
            progress(
                "the final joint refit loses a cause: the selection's model stays"
                if len(alt[1]) > len(kept)
                else "the selection's model fits the report data better: it stays"
            )
            final = sel
            findings, kept, ext_sum, y_ext = alt
    for name in accepted:
        if name not in kept:
            progress(f"{name} does not raise the report fit: not accepted")
            rows[name] = dataclasses.replace(
                rows[name],
                accepted=False,
                note="lowers the report fit: not accepted",
            )
    refitted = bool(kept) or ext_sum.fit_percent > base_sum.fit_percent
    if refitted and not kept:
        progress(
            f"the joint refit on more data moves the seed's parameters: report fit "
            f"{base_sum.fit_percent:.1f} -> {ext_sum.fit_percent:.1f} % without a cause"
        )
    return Refit(final, base_pol, base_sum, y_base, findings, kept, ext_sum, y_ext, rows, refitted)


_Kept = tuple[list[Finding], list[str], ModelSummary, np.ndarray]


def _keep(
    model: FitResult,
    accepted: Sequence[str],
    by_name: dict[str, Candidate],
    report: Sequence[Series],
    base_sum: ModelSummary,
    y_base: np.ndarray,
) -> _Kept:
    """The accepted causes that earn their place in ``model`` on the report data, in
    order: each must raise the report fit of ``model``'s own parameters (a cause's gain
    is what switching it on adds, not what the joint refit moved in the seed's
    parameters: a cause fitted to nothing, its parameter 1e-12 of its scale, adds
    nothing), and the model with them must beat the seed's (``base_sum``).  With none
    kept, the report figures of ``model``'s parameters without its causes when they beat
    the seed's (the joint refit on more data found a better seed), else the seed's.
    Each finding's ``fit_gain_percent`` is what it adds to the ones before it, the first
    counted from the better of the seed's fit and ``model``'s without causes: they add
    up to the extended model's fit minus that (switching every cause off at the joint
    refit's parameters may fit far below the seed: the first cause was credited +52
    points where the extended model gained 2)."""
    found: list[Finding] = []
    kept_: list[str] = []
    off = {by_name[a].param.name: 0.0 for a in accepted}
    e_sum, y_e = summary(model.params, dataclasses.replace(model.effects, **off), report)
    ref = max(e_sum.fit_percent, base_sum.fit_percent)
    least = ACTS_MIN * float(np.std(y_base))  # a change of the speed this small is none
    for name in accepted:
        later = {by_name[a].param.name: 0.0 for a in accepted if a not in (*kept_, name)}
        trial = dataclasses.replace(model.effects, **later)
        s_k, y_k = summary(model.params, trial, report)
        if s_k.fit_percent <= e_sum.fit_percent or s_k.fit_percent <= base_sum.fit_percent:
            continue
        if float(np.sqrt(np.mean(np.square(y_k - y_e)))) < least:
            continue
        found.append(
            Finding(
                name=by_name[name].output or name,
                params=params_of(by_name[name], model.effects),
                profile=profile_of(by_name[name], model.effects),
                fit_percent=s_k.fit_percent,
                fit_gain_percent=s_k.fit_percent - max(e_sum.fit_percent, ref),
            )
        )
        kept_.append(name)
        e_sum, y_e = s_k, y_k
    if not kept_ and e_sum.fit_percent <= base_sum.fit_percent:  # the seed's, as it was
        e_sum, y_e = base_sum, y_base
    if len(kept_) < len(accepted) > 1:  # causes that act together (a pair)
        together = _together(model, [by_name[a] for a in accepted], report, e_sum, least, ref)
        if together is not None:
            return together
    return found, kept_, e_sum, y_e


def _together(
    model: FitResult,
    causes: Sequence[Candidate],
    report: Sequence[Series],
    best: ModelSummary,
    least: float,
    ref: float,
) -> _Kept | None:
    """All of ``causes`` in ``model``, when they earn their place only together: the model
    with all of them beats ``best`` (what one at a time kept) on the report data, and
    switching any one of them off lowers that fit (what it adds to the others) and moves
    the speed by ``least`` (m/s RMS) at least.  Their ``fit_gain_percent`` share the
    gain over ``ref`` (the fit they are counted from, :func:`_keep`) in proportion to
    what each adds to the others.  A cause fitted jointly with another (the battery's sag
    with the loop's own delay) may be worse alone than none at all; None when they do
    not."""
    full, y_full = summary(model.params, model.effects, report)
    if full.fit_percent <= best.fit_percent:
        return None
    adds: list[float] = []
    for c in causes:
        off = dataclasses.replace(model.effects, **{c.param.name: 0.0})
        s_off, y_off = summary(model.params, off, report)
        gain = full.fit_percent - s_off.fit_percent
        if gain <= 0.0 or float(np.sqrt(np.mean(np.square(y_full - y_off)))) < least:
            return None
        adds.append(gain)
    total = max(full.fit_percent - ref, 0.0)
    found = [
        Finding(
            name=c.output or c.name,
            params=params_of(c, model.effects),
            profile=profile_of(c, model.effects),
            fit_percent=full.fit_percent,
            fit_gain_percent=total * a / sum(adds),
        )
        for c, a in zip(causes, adds, strict=True)
    ]
    return found, [c.name for c in causes], full, y_full
