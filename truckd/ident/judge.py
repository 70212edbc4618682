"""Whether a model earns one more cause: the tests of the candidate and selection
stages of :mod:`truckd.ident.diagnose`.

Besides the information criterion and the validation cost
(:func:`passes_over`), a cause must raise the validation fit
where it acts (:data:`truckd.ident.scoring.GAIN_MIN`), or lower the validation cost by
:data:`STRONG_REL`, and be physically possible; a
hill, which changes nothing off its stretch, is validated where it acts, or on
held-out crossings of its stretch.  Pure numerics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from truckd.ident.candidates import (
    Candidate,
)
from truckd.ident.data import (
    MIN_RUN,
    Series,
    noise_std,
)
from truckd.ident.physics import (
    effect_problem,
    fitted_mass,
)
from truckd.ident.result import (
    Rejected,
)
from truckd.ident.runs import Prepared
from truckd.ident.scoring import (
    GAIN_MIN,
    MIN_SUPPORT,
    Model,
    gain_where_acting,
)
from truckd.ident.selection import BIC_MIN, REL_MIN, delta_bic, passes
from truckd.ident.terrain import (
    hill_problem,
    rolling_problem,
    time_constant,
)
from truckd.ident.voltage import (
    FitResult,
    Weights,
    residuals,
    scan,
)
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

STRONG_REL = 0.2
"""A cause that lowers the validation cost by this share earns its place without the
points of fit where it acts: those points depend on how widely the speed spreads where the
cause acts, not on how much of the model's error it removes.  A Stribeck friction of
0.006 N m in the default truck's log lowers the validation cost by 28 % and gains 0.26
points (the controller then recovers 0.7 of its gap error); no other candidate lowered
that log's validation cost by more than 2 %."""

SETTLE = 3.0
"""A hill acts on the speed while the truck is on its stretch and for about this many
mechanical time constants after it left: its validation is judged on those samples."""


def hill_support(p: VehicleParams, e: Effects, data: Sequence[Series], w: Weights) -> np.ndarray:
    """Which entries of :func:`residuals` over ``data`` the hill of ``e`` acts on: the
    samples on its stretch and up to :data:`SETTLE` time constants after leaving it
    (of a held speed, the fresh readings, as the residuals count them)."""
    settle = SETTLE * (time_constant(p) or 0.0)
    lo, hi = e.hill_start, e.hill_start + e.hill_length
    parts = []
    for s in data:
        on = np.zeros(len(s), dtype=bool) if s.x is None else (s.x >= lo) & (s.x < hi)
        last = np.maximum.accumulate(np.where(on, s.t, -np.inf))
        near = s.t - last <= settle
        parts.append(near if s.all_fresh else near[s.fresh])  # as residuals() counts
        if w.i and s.i is not None:
            parts.append(near[1:])
    return np.concatenate(parts) if parts else np.zeros(0, dtype=bool)


def hill_val_costs(
    new: FitResult, old: FitResult, hill: Effects, val: Sequence[Series], w: Weights
) -> tuple[float, float] | None:
    """Validation costs of ``new`` and ``old`` where the hill of ``hill`` acts (None: the
    validation data hardly reach its stretch)."""
    mask = hill_support(new.params, hill, val, w)
    if int(mask.sum()) < MIN_SUPPORT:
        return None
    r_new = residuals(new.params, new.effects, val, w)[mask]
    r_old = residuals(old.params, old.effects, val, w)[mask]
    return float(r_new @ r_new), float(r_old @ r_old)


def crossings(p: VehicleParams, hill: Effects, runs: Sequence[Series]) -> list[Series]:
    """The visits of ``runs`` to the hill's stretch, each a piece of its run from one
    time constant before the truck reached the stretch (its measured state then) to
    :data:`SETTLE` time constants after it left; overlapping visits are merged."""
    tau = time_constant(p) or 0.0
    lo, hi = hill.hill_start, hill.hill_start + hill.hill_length
    out: list[Series] = []
    for r in runs:
        if r.x is None or len(r) < 2:
            continue
        on = (r.x >= lo) & (r.x < hi)
        if not on.any():
            continue
        h = float(np.median(np.diff(r.t)))
        pre = max(5, int(np.ceil(tau / h)))
        post = max(5, int(np.ceil(SETTLE * tau / h)))
        edges = np.diff(np.concatenate([[0], on.astype(int), [0]]))
        starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
        pieces: list[list[int]] = []
        for k0, k1 in zip(starts, ends, strict=True):
            a, b = max(0, int(k0) - pre), min(len(r), int(k1) + post)
            if pieces and a <= pieces[-1][1]:
                pieces[-1][1] = max(pieces[-1][1], b)
            else:
                pieces.append([a, b])
        out.extend(r.slice(a, b) for a, b in pieces if b - a >= MIN_RUN)
    return out


def held_out_crossings(
    model: FitResult, hill: Effects, est: Sequence[Series], w: Weights
) -> bool | None:
    """A hill validated on held-out crossings of the estimation runs (when the
    validation data do not reach its stretch): the visits to the stretch in two folds
    (alternate visits), the hill's force fitted on one fold (the rest of ``model``
    held; ``hill`` gives the stretch) must lower the other fold's cost by
    :data:`REL_MIN`, both ways.  None: fewer than two visits."""
    visits = crossings(model.params, hill, est)
    folds = [visits[0::2], visits[1::2]]
    if not folds[1] or min(sum(len(v) for v in f) for f in folds) < MIN_SUPPORT:
        return None
    e = dataclasses.replace(model.effects, hill_start=hill.hill_start, hill_length=hill.hill_length)
    grid = sorted(float(k) * hill.hill_force for k in np.linspace(0.0, 2.0, 21))
    for own, other in ((0, 1), (1, 0)):
        force, _ = scan(model.params, e, "hill_force", grid, folds[own], w)
        r_new = residuals(model.params, dataclasses.replace(e, hill_force=force), folds[other], w)
        r_old = residuals(model.params, dataclasses.replace(e, hill_force=0.0), folds[other], w)
        if not float(r_new @ r_new) < (1.0 - REL_MIN) * float(r_old @ r_old):
            return False
    return True


def bic_change(new: FitResult, old: FitResult, extra: int) -> float:
    return delta_bic(new.sse, old.sse, old.n, extra)


def passes_over(
    new: Model, old: Model, extra: int, hill_ok: bool | None = None
) -> tuple[bool, float]:
    """Whether ``new`` earns its place over ``old`` (:func:`selection.passes`) and the
    change of the information criterion.  When the difference is a hill, ``hill_ok``
    replaces the validation test (a load on a stretch of road changes nothing
    elsewhere: it is validated where it acts)."""
    dbic = bic_change(new.fit, old.fit, extra)
    if hill_ok is None:
        return passes(dbic, new.val_cost, old.val_cost), dbic
    return dbic < -BIC_MIN and hill_ok, dbic


class Judge:
    """The tests a model must pass to take one more cause, for the candidate and the
    selection stages alike, with what they record on the way: the causes rejected as
    physically impossible, a note per hill that could not be validated, and the
    held-out verdicts already reached."""

    def __init__(self, prep: Prepared, by_name: dict[str, Candidate]) -> None:
        self.prep = prep
        self.by_name = by_name
        self.rejected: list[Rejected] = []
        self.hill_notes: dict[str, str] = {}
        self.held_out: dict[tuple[float, float, float], bool | None] = {}
        self.noise_val = float(np.mean([noise_std(r.v) for r in prep.val]))

    def possible(self, m: FitResult, names: Sequence[str]) -> bool:
        """Every effect of ``m`` physically possible; else recorded as rejected."""
        runs, p0 = self.prep.runs, self.prep.p0
        ok = True
        for n in names:
            pn = self.by_name[n].param.name
            e = m.effects
            mass = fitted_mass(m.params, p0)
            if pn == "hill_force":
                why = hill_problem(e.hill_force, e.hill_start, e.hill_length, m.params, runs, mass)
            elif pn == "load_force_amplitude":
                why = rolling_problem(
                    e.load_force_amplitude, e.load_force_wavelength, m.params, runs, mass
                )
            else:
                why = effect_problem(n, float(getattr(m.effects, pn)), m.params, runs, p0)
            if why is not None:
                ok = False
                # one row per candidate: its first impossible fit (later tries on top of
                # other causes repeat it with other numbers)
                if all(r.name != n for r in self.rejected):
                    self.rejected.append(Rejected(n, {pn: float(getattr(m.effects, pn))}, why))
        return ok

    def is_hill(self, name: str) -> bool:
        return self.by_name[name].param.name == "hill_force"

    def earns(self, name: str, new: Model, old: Model) -> bool:
        """``new`` (``old`` + ``name``) raises the validation fit where the cause acts
        by :data:`GAIN_MIN` points, or lowers the validation cost by :data:`STRONG_REL`
        (a hill: validated where it acts, :meth:`hill_check`)."""
        if self.is_hill(name) or new.val_cost < (1.0 - STRONG_REL) * old.val_cost:
            return True
        return gain_where_acting(new.fit, old.fit, self.prep.val, self.noise_val) >= GAIN_MIN

    def hill_check(self, name: str, new: Model, old: Model) -> bool | None:
        """The validation of the hill of ``new`` when ``name`` is the hill (else None):
        ``new`` lowers the validation cost where the hill acts by :data:`REL_MIN` (and
        raises it nowhere); when the validation data do not reach the stretch, its
        held-out crossings decide."""
        if not self.is_hill(name):
            return None
        if new.val_cost > old.val_cost:
            self.hill_notes[name] = "raises the validation cost"
            return False  # the hill acts nowhere else: a worse validation is the rest's
        e = new.fit.effects
        costs = hill_val_costs(new.fit, old.fit, e, self.prep.val_data, self.prep.w)
        if costs is not None:
            return costs[0] < (1.0 - REL_MIN) * costs[1]
        key = (e.hill_force, e.hill_start, e.hill_length)
        if key not in self.held_out:
            self.held_out[key] = held_out_crossings(new.fit, e, self.prep.est, self.prep.w)
        if self.held_out[key] is None:
            self.hill_notes[name] = "not validated: no held-out data reach the stretch twice"
            return False
        return self.held_out[key]

    def takes(self, name: str, new: Model, old: Model) -> tuple[bool, float]:
        """Whether ``new`` (``old`` + ``name``) earns its place by both tests of the
        selection (:func:`passes_over`, the hill's own validation) and by
        :meth:`earns`; and the change of the information criterion."""
        ok, dbic = passes_over(new, old, 1, self.hill_check(name, new, old))
        return ok and self.earns(name, new, old), dbic
