"""Stage 5 of the diagnosis (:mod:`truckd.ident.diagnose`): the selection.

The candidates that passed alone are taken greedily, strongest first, each refitted
jointly with those already accepted; while the residual keeps structure (on the
validation or the estimation runs) the rest are tried on top; when one cause is not
enough, the best pair (:mod:`truckd.ident.pairs`); last, a backward check drops a cause
the others make redundant.  Pure numerics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

from truckd.ident.candidates import (
    Candidate,
    fit_work,
)
from truckd.ident.extend import fit_candidate
from truckd.ident.fanout import Mapper, as_start, in_order, kept_lines, side_by_side
from truckd.ident.judge import passes_over
from truckd.ident.pairs import PAIR_TOP, best_pair, pair_order
from truckd.ident.result import (
    CandidateRow,
)
from truckd.ident.runs import Prepared
from truckd.ident.scoring import Model, Progress, still_structured, val_cost
from truckd.ident.seed import Seed
from truckd.ident.selection import (
    close,
)
from truckd.ident.trials import Trials
from truckd.ident.voltage import (
    FitResult,
    Param,
    fit_with_stiction,
)

MAX_EXTRA_ROUNDS = 2
"""Rounds of trying the remaining candidates on top of the accepted ones."""

IDLE_GAIN = 1e-6
"""A candidate whose fit on top of the model lowers its cost on the fit data by less than
this fraction changes nothing there (its parameter stays where it does nothing): the
next round, one more cause on top, does not try it again."""


@dataclass(frozen=True)
class Choice:
    """What the selection stage hands on."""

    current: Model
    """The selected model (the seed with the accepted causes, jointly fitted)."""
    accepted: list[str]
    """The accepted candidates, in the order they were taken."""
    ambiguous: list[tuple[str, str]]
    """Pairs (accepted, other) the data cannot tell apart."""
    rows: dict[str, CandidateRow]
    """The candidates' rows with the selection's notes."""


@dataclass
class _Selecting:
    """The selection under way: what each of its steps reads and changes."""

    prep: Prepared
    seed: Seed
    trials: Trials
    progress: Progress
    current: Model
    accepted: list[str] = field(default_factory=list)
    ambiguous: list[tuple[str, str]] = field(default_factory=list)
    rows: dict[str, CandidateRow] = field(default_factory=dict)
    mapper: Mapper = in_order
    """How a list of independent fits runs (:mod:`truckd.ident.fanout`)."""
    fitted: dict[tuple[int, tuple[Param, ...], str], tuple[FitResult, FitResult]] = field(
        default_factory=dict
    )
    """Fits done, by start model (identity), parameters freed and candidate: the greedy
    joint refit of two causes and the pair of the same two from the same start are one
    fit (the start is kept with the result, so its identity is not reused)."""
    ahead: dict[tuple[int, tuple[Param, ...], str], list[str]] = field(default_factory=dict)
    """The progress lines of fits done ahead of their turn (:meth:`fit_ahead`), said when
    :meth:`fit_all` reaches them."""

    def fit(self, base: FitResult, extra: list[Param], cand: Candidate) -> FitResult:
        """``base`` + ``cand`` fitted (:func:`fit_candidate`) with ``extra`` freed; the
        same fit again is not redone (the fit is deterministic)."""
        return self.fit_all([(base, extra, cand, None)])[0]

    def fit_all(
        self, jobs: Sequence[tuple[FitResult, list[Param], Candidate, str | None]]
    ) -> list[FitResult]:
        """:meth:`fit` of each ``(base, extra, cand, header)``, the header said before
        the fit's progress.  The fits not done already run through :attr:`mapper`; the
        progress reads as the plain loop says it, in the jobs' order."""
        keys = [(id(base), tuple(extra), cand.name) for base, extra, cand, _ in jobs]
        todo: list[int] = []
        for k, (base, _, _, _) in enumerate(jobs):
            hit = self.fitted.get(keys[k])
            fresh = hit is None or hit[0] is not base
            if fresh and keys[k] not in (keys[j] for j in todo):
                todo.append(k)

        def one(k: int, say: Progress) -> FitResult:
            base, extra, cand, _ = jobs[k]
            return self._fitted(base, extra, cand, say)

        said: dict[int, list[str]] = {}
        if self.mapper is not in_order and len(todo) > 1:

            def work(k: int) -> float:
                return fit_work(jobs[k][2]) + len(jobs[k][1])

            ran = kept_lines(self.mapper, one, todo, work)
            for k, (out, lines) in zip(todo, ran, strict=True):
                base = jobs[k][0]
                self.fitted[keys[k]] = (base, as_start(out, base))
                said[k] = lines
        results = []
        for k, (base, extra, cand, header) in enumerate(jobs):
            if header is not None:
                self.progress(header)
            if k in said:
                for line in said[k]:
                    self.progress(line)
            elif k in todo:
                self.fitted[keys[k]] = (base, one(k, self.progress))
            elif keys[k] in self.ahead:  # fitted ahead: its lines now, as the loop says them
                for line in self.ahead.pop(keys[k]):
                    self.progress(line)
            else:
                self.progress(f"  {cand.name} with {[x.name for x in extra]} freed: fitted above")
            results.append(self.fitted[keys[k]][1])
        return results

    def fit_ahead(self, jobs: Sequence[tuple[FitResult, list[Param], Candidate]]) -> None:
        """:meth:`fit` of each ``(base, extra, cand)`` now, side by side through
        :attr:`mapper`, each kept with its progress lines for when :meth:`fit_all` reaches
        it: a guess at the fits that come next, which costs a worker's time when wrong,
        never a result (a fit is deterministic).  Nothing where the fits would run one
        after another (the plain loop, or workers that cannot fork here)."""
        if not side_by_side(self.mapper):
            return
        todo: list[tuple[FitResult, list[Param], Candidate]] = []
        for base, extra, cand in jobs:
            key = (id(base), tuple(extra), cand.name)
            hit = self.fitted.get(key)
            if (hit is None or hit[0] is not base) and all(
                (id(b), tuple(e), c.name) != key for b, e, c in todo
            ):
                todo.append((base, extra, cand))
        if len(todo) < 2:
            return

        def one(job: tuple[FitResult, list[Param], Candidate], say: Progress) -> FitResult:
            return self._fitted(*job, say)

        ran = kept_lines(self.mapper, one, todo, lambda j: fit_work(j[2]) + len(j[1]))
        for (base, extra, cand), (out, lines) in zip(todo, ran, strict=True):
            key = (id(base), tuple(extra), cand.name)
            self.fitted[key] = (base, as_start(out, base))
            self.ahead[key] = lines

    def _fitted(
        self, base: FitResult, extra: list[Param], cand: Candidate, say: Progress
    ) -> FitResult:
        """:func:`fit_candidate` of ``base`` + ``cand`` with ``extra`` freed."""
        p = self.prep
        return fit_candidate(
            base, self.seed.free, extra, cand, p.fit_data, p.w, self.seed.grid, say, p.val_data
        )

    def smooth_params(self, names: Sequence[str]) -> list[Param]:
        """The parameters of ``names`` a joint refit frees (the smooth ones)."""
        by_name = self.trials.by_name
        return [by_name[a].param for a in names if by_name[a].smooth]

    def note(self, name: str, note: str, accepted: bool | None = None) -> None:
        row = self.rows[name]
        self.rows[name] = dataclasses.replace(
            row, note=note, accepted=row.accepted if accepted is None else accepted
        )


def selection_stage(
    prep: Prepared, seed: Seed, trials: Trials, progress: Progress, mapper: Mapper = in_order
) -> Choice:
    """Stage 5 of the diagnosis: the candidates that passed alone taken greedily, the
    rest tried on top while structure remains, a pair of causes when one is not
    enough, then a backward check (see :mod:`truckd.ident.diagnose`); the fits that do
    not depend on each other run through ``mapper`` (:mod:`truckd.ident.fanout`)."""
    s = _Selecting(prep, seed, trials, progress, seed.model, rows=dict(trials.rows), mapper=mapper)
    _greedy(s)
    _extra_rounds(s)
    if len(s.accepted) < 2:
        _pair(s)
    if len(s.accepted) > 1:
        _backward(s)
    return Choice(s.current, s.accepted, s.ambiguous, s.rows)


def _evidence(m: Model, base: Model) -> float:
    """How much better ``m`` explains all the data than ``base`` (lower: better): the
    product of its cost ratios on the fit data and on the validation data.  Either set
    alone can mislead: a short validation chirp can prefer a sensor lag (with a smaller
    inertia) to the dead zone the steps show plainly."""
    fit_ratio = m.fit.sse / base.fit.sse if base.fit.sse > 0.0 else 1.0
    val_ratio = m.val_cost / base.val_cost if base.val_cost > 0.0 else 1.0
    return fit_ratio * val_ratio


def _with_delay(
    tried: dict[str, Model], base: Model, skip: Sequence[str], order: Sequence[tuple[str, str]]
) -> list[tuple[str, str]]:
    """Pairs of the strongest causes on all the data (:func:`_evidence`) with an input
    delay: every digital loop has one (a part of a period and more), and a cause fitted
    without it can validate worse than none at all on a chirp, as can the delay alone."""
    if "input_delay" not in tried or "input_delay" in skip:
        return []
    strongest = sorted(
        (n for n in tried if n != "input_delay" and n not in skip),
        key=lambda n: _evidence(tried[n], base),
    )[:PAIR_TOP]
    have = {frozenset(ab) for ab in order}
    return [(n, "input_delay") for n in strongest if frozenset((n, "input_delay")) not in have]


def _greedy(s: _Selecting) -> None:
    """The candidates that passed alone, strongest first, each refitted jointly with
    those already accepted; one that adds nothing is ambiguous with a rival or not
    taken."""
    tried, by_name, judge = s.trials.tried, s.trials.by_name, s.trials.judge
    passing = sorted(
        (n for n, r in s.rows.items() if r.note == "passes alone"),
        key=lambda n: _evidence(tried[n], s.seed.model),
    )
    if len(passing) > 2:
        # Through workers, the joint refits that follow the strongest fitted side by side,
        # on the guess that it is taken and each of them is not (they all start from it).
        top = passing[0]
        extra = s.smooth_params([top])
        s.fit_ahead([(tried[top].fit, extra, by_name[n]) for n in passing[1:]])
    for name in passing:
        cand = by_name[name]
        if not s.accepted:
            new = tried[name]
        else:
            s.progress(f"joint refit: {', '.join(s.accepted)} + {name}")
            f = s.fit(s.current.fit, s.smooth_params(s.accepted), cand)
            new = Model(f, (*s.current.names, name), val_cost(f, s.prep.val_data, s.prep.w))
        ok, _ = judge.takes(name, new, s.current)
        if ok and judge.possible(new.fit, [*s.accepted, name]):
            s.accepted.append(name)
            s.current = new
            s.note(name, "accepted", True)
            continue
        rival = _rival(s, name)
        if rival is not None:
            s.ambiguous.append((rival, name))
            s.note(name, f"ambiguous with {rival}")
        else:
            s.note(name, "adds nothing once others are in")


def _extra_rounds(s: _Selecting) -> None:
    """A weaker effect can be masked by a stronger one when tried alone: while the
    residual still has structure (:func:`_structure_remains`), try the rest on top of the
    current model."""
    judge = s.trials.judge
    idle: set[str] = set()
    for _ in range(MAX_EXTRA_ROUNDS):
        if not s.accepted or not _structure_remains(s):
            break
        taken = set(s.accepted) | {b for _, b in s.ambiguous} | idle
        rest = [c for c in s.trials.cands if c.name not in taken]
        if not rest:
            break
        extra = s.smooth_params(s.accepted)
        best: Model | None = None
        on_top = ", ".join(s.accepted)
        fits = s.fit_all(
            [
                (s.current.fit, extra, c, f"structure remains: trying {c.name} on top of {on_top}")
                for c in rest
            ]
        )
        for cand, f in zip(rest, fits, strict=True):
            if f.sse > s.current.fit.sse * (1.0 - IDLE_GAIN):
                idle.add(cand.name)
            new = Model(f, (*s.current.names, cand.name), val_cost(f, s.prep.val_data, s.prep.w))
            if (
                judge.takes(cand.name, new, s.current)[0]
                and judge.possible(new.fit, new.names)
                and (best is None or new.val_cost < best.val_cost)
            ):
                best = new
        if best is None:
            break
        name = best.names[-1]
        s.accepted.append(name)
        s.current = best
        s.note(name, "accepted on top of the others", True)


def _structure_remains(s: _Selecting) -> bool:
    """The current model's free-run residual has structure on the validation runs or on
    the estimation runs.  A validation chirp alone can hide what the ramps and steps show:
    a constant load force on a truck with a long dead time (the delay the only cause
    passing alone, the force masked by it) leaves the chirp's residual white while the
    forward runs stay shorter than the reverse ones."""
    return still_structured(s.current.fit, s.prep.val) or still_structured(
        s.current.fit, s.prep.est
    )


def _pair(s: _Selecting) -> None:
    """Pairs of causes, when one is not enough (:mod:`truckd.ident.pairs`): each member
    must earn its place against the other alone, the pair against the greedy model."""
    tried, by_name, judge = s.trials.tried, s.trials.by_name, s.trials.judge

    def own(a: str) -> list[Param]:
        ca = by_name[a]
        return [ca.param, *ca.extra] if ca.smooth else []

    def fit_pair(a: str, b: str) -> Model | None:
        f = fitted_pairs[(a, b)]
        m = Model(f, (a, b), val_cost(f, s.prep.val_data, s.prep.w))
        return m if judge.possible(m.fit, [a, b]) else None

    def member_earns(m: Model, name: str) -> bool:
        other = tried[m.names[1] if name == m.names[0] else m.names[0]]
        return judge.takes(name, m, other)[0]

    single = {n: m.val_cost for n, m in tried.items()}
    impossible = [n for n, r in s.rows.items() if r.note.startswith("physically impossible")]
    order = pair_order(single, s.seed.model.val_cost, skip=impossible, accepted=s.accepted)
    order += _with_delay(tried, s.seed.model, impossible, order)
    jobs = [(tried[a].fit, own(a), by_name[b], f"pair: {a} + {b}") for a, b in order]
    fitted_pairs = dict(zip(order, s.fit_all(jobs), strict=True))
    pair = best_pair(order, s.current.val_cost, fit_pair, lambda m: m.val_cost, member_earns)
    if pair is None:
        return
    for n in s.accepted:
        if n not in pair.names:
            s.note(n, "replaced by a pair of causes", False)
    for n in pair.names:
        other = pair.names[1] if n == pair.names[0] else pair.names[0]
        s.note(n, f"accepted with {other} (a pair)", True)
    s.accepted, s.current = list(pair.names), pair


def _backward(s: _Selecting) -> None:
    """An effect accepted early may be redundant once later ones are in.  Through a
    mapper, the model without each cause is fitted ahead from the same current model;
    once a cause is dropped, the later checks are fitted again from the new model (the
    progress as one check after another says it)."""
    p, by_name = s.prep, s.trials.by_name

    def without(start: Model, accepted: list[str], name: str, say: Progress) -> Model:
        others = [a for a in accepted if a != name]
        say(f"backward check: {', '.join(others)} without {name}")
        off = dataclasses.replace(start.fit.effects, **{by_name[name].param.name: 0.0})
        free = [*s.seed.free, *s.smooth_params(others)]
        f = fit_with_stiction(start.fit.params, off, free, p.fit_data, p.w, s.seed.grid, say)
        return Model(f, tuple(others), val_cost(f, p.val_data, p.w))

    first, names = s.current, list(s.accepted)
    ahead: list[tuple[Model, list[str]]] | None = None
    if s.mapper is not in_order:
        ahead = kept_lines(
            s.mapper, lambda n, say: without(first, names, n, say), names,
            lambda n: fit_work(by_name[n]),
        )  # fmt: skip
    for k, name in enumerate(names):
        if ahead is not None and s.current is first:
            reduced, lines = ahead[k]
            for line in lines:
                s.progress(line)
        else:
            reduced = without(s.current, s.accepted, name, s.progress)
        ok_hill = s.trials.judge.hill_check(name, s.current, reduced)
        if not passes_over(s.current, reduced, 1, ok_hill)[0]:
            s.accepted.remove(name)
            s.current = reduced
            s.note(name, "redundant once the others are in", False)


def _rival(s: _Selecting, name: str) -> str | None:
    """The accepted effect that ``name`` can replace equally well, if any.

    Tried only for rivals that explained about as much alone: swap one for the other
    in the current model, refit, and compare the validation costs.
    """
    tried, by_name = s.trials.tried, s.trials.by_name
    for a in s.accepted:
        if not close(tried[name].val_cost, tried[a].val_cost):
            continue
        s.progress(f"swap test: {name} instead of {a}")
        off = dataclasses.replace(s.current.fit.effects, **{by_name[a].param.name: 0.0})
        base = FitResult(s.current.fit.params, off, float("inf"), s.current.fit.n, 0)
        extra = s.smooth_params([x for x in s.accepted if x != a])
        f = fit_candidate(
            base, s.seed.free, extra, by_name[name], s.prep.fit_data, s.prep.w, s.seed.grid,
            s.progress,
        )  # fmt: skip
        if close(val_cost(f, s.prep.val_data, s.prep.w), s.current.val_cost):
            return a
    return None
