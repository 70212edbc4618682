"""Stage 4 of the diagnosis (:mod:`truckd.ident.diagnose`): the candidates, each alone.

Every effect of :mod:`truckd.ident.candidates`, and a hill or rolling terrain when
the seed's residual locates one, fitted alone on top of the seed and judged against
it (:class:`truckd.ident.judge.Judge`).  Pure numerics.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from truckd.ident.candidates import (
    Candidate,
    fit_work,
    hill_candidate,
    rolling_candidate,
    voltage_candidates,
)
from truckd.ident.extend import fit_candidate, params_of
from truckd.ident.fanout import Mapper, as_start, fan_out, in_order
from truckd.ident.judge import Judge
from truckd.ident.result import (
    CandidateRow,
)
from truckd.ident.runs import Prepared
from truckd.ident.scoring import Model, Progress, summary, val_cost
from truckd.ident.seed import Seed
from truckd.ident.terrain import (
    locate,
    locate_wave,
)


@dataclass(frozen=True)
class Trials:
    """What the candidate stage hands on."""

    cands: list[Candidate]
    """The candidates tried, in order (the located hill and rolling terrain last)."""
    by_name: dict[str, Candidate]
    tried: dict[str, Model]
    """Each candidate alone on top of the seed."""
    rows: dict[str, CandidateRow]
    """Each candidate's row of the table, as tried alone."""
    judge: Judge
    """The selection's tests (the selection stage goes on using them)."""


def candidates_stage(
    prep: Prepared, seed: Seed, progress: Progress, mapper: Mapper = in_order
) -> Trials:
    """Stage 4 of the diagnosis: the candidates (the effects, and a hill or rolling
    terrain located in the seed's residual), each fitted alone on top of the seed
    and judged against it; the fits run through ``mapper``
    (:mod:`truckd.ident.fanout`), the judging after them, in order."""
    base_fit, base = seed.fit, seed.model
    cands = voltage_candidates(base_fit.params, prep.whole)
    stretch = locate(base_fit.params, prep.runs)
    if stretch is not None:
        progress(
            f"residual localised on [{stretch.start:.3g}, {stretch.start + stretch.length:.3g}]"
            f" m ({stretch.force:.3g} N): hill candidate"
        )
        cands.append(hill_candidate(base_fit.params, stretch))
    wave = locate_wave(base_fit.params, prep.runs)
    if wave is not None:
        progress(f"residual periodic in position ({wave.wavelength:.3g} m): rolling candidate")
        cands.append(rolling_candidate(base_fit.params, wave))
    by_name = {c.name: c for c in cands}
    judge = Judge(prep, by_name)
    tried: dict[str, Model] = {}
    rows: dict[str, CandidateRow] = {}
    base_fit_pct = summary(base_fit.params, base_fit.effects, prep.val)[0].fit_percent

    def alone(k: int, say: Progress) -> tuple[Model, float]:
        cand = cands[k]
        say(f"candidate {k + 1}/{len(cands)}: {cand.name}")
        f = fit_candidate(
            base_fit, seed.free, [], cand, prep.fit_data, prep.w, seed.grid, say, prep.val_data
        )
        m = Model(f, (cand.name,), val_cost(f, prep.val_data, prep.w))
        return m, summary(f.params, f.effects, prep.val)[0].fit_percent

    fitted = fan_out(mapper, alone, range(len(cands)), progress, lambda k: fit_work(cands[k]))
    for cand, (m, fp) in zip(cands, fitted, strict=True):
        if (start := as_start(m.fit, base_fit)) is not m.fit:
            m = dataclasses.replace(m, fit=start)
        f = m.fit
        ok, dbic = judge.takes(cand.name, m, base)
        note = "passes alone" if ok else judge.hill_notes.get(cand.name, "")
        if ok and not judge.possible(f, [cand.name]):
            ok = False
            why = next(r.reason for r in judge.rejected if r.name == cand.name)
            note = f"physically impossible: {why}"
        tried[cand.name] = m
        rows[cand.name] = CandidateRow(
            name=cand.name,
            params=params_of(cand, f.effects),
            fit_percent=fp,
            gain_percent=fp - base_fit_pct,
            cost_ratio=m.val_cost / base.val_cost if base.val_cost > 0 else 1.0,
            delta_bic=dbic,
            accepted=False,
            note=note,
        )
    return Trials(cands, by_name, tried, rows, judge)
