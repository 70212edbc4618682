"""Diagnosis of a voltage-input log: seed fit, candidates, selection, joint refit.

1. Fit the seed (motor, inertia, Coulomb, stiction) by simulation error on the
   estimation data (the log, or its first 70 % when no validation log is given).
2. Try each candidate effect alone on top of the seed (grid start, joint refit).
3. A candidate earns its place when it lowers the information criterion on the
   estimation data (``delta BIC < -BIC_MIN``) *and* the validation cost by at least
   ``REL_MIN``.  Accept them greedily, strongest first, each refitted jointly with
   those already accepted; a candidate that passed alone but adds nothing once a rival
   is in, while having explained about as much alone, is reported as ``ambiguous``.
4. The residual of the extended model on the report data decides ``unexplained``:
   it is not white (autocorrelation beyond the 99 % band at many lags) and its RMS
   clearly exceeds the measurement noise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.candidates import (
    Candidate,
    hill_candidate,
    rolling_candidate,
    voltage_candidates,
)
from truckd.ident.data import (
    MIN_RUN,
    Series,
    chunks_of_runs,
    fresh_mask,
    merged,
    noise_std,
    split_runs_for_validation,
    with_position,
)
from truckd.ident.linear import (
    Feedforward,
    LeastSquares,
    feedforward_of,
    least_squares_model,
    start_model,
)
from truckd.ident.pairs import PAIR_TOP, best_pair, pair_order
from truckd.ident.physics import (
    configuration_notes,
    effect_problem,
    effects_problems,
    vehicle_problems,
)
from truckd.ident.residuals import Whiteness, looks_like, whiteness
from truckd.ident.result import (
    CandidateRow,
    Diagnosis,
    Finding,
    ModelSummary,
    Rejected,
    Traces,
)
from truckd.ident.selection import (
    BIC_MIN,
    REL_MIN,
    close,
    delta_bic,
    passes,
    structured,
    white,
)
from truckd.ident.terrain import (
    hill_problem,
    locate,
    locate_wave,
    rolling_problem,
    time_constant,
)
from truckd.ident.voltage import (
    FitResult,
    Param,
    Weights,
    apply,
    fit_percent,
    fit_with_stiction,
    predict,
    residuals,
    rmse,
    scan,
    scan_stiction,
    seed_params,
    stiction_grid,
    theta_of,
    weights_for,
)
from truckd.model.effects import COMPANIONS, Effects
from truckd.model.params import VehicleParams

Progress = Callable[[str], None]

FIT_BUDGET = 4000
"""Samples of the estimation data used in the fitting loop (spread over chunks): at
least, and at least 40 s of it (a faster log gets more samples, up to five times: at
1 kHz 4000 samples were 1 s chunks, shorter than a slow truck's response, and the fit
took a sensor lag for inertia)."""
FINAL_BUDGET = 8000
"""Samples used by the final joint refit of the extended model (at least 80 s, as above)."""
FINAL_NFEV = 80
"""Evaluations of the final joint refit (R_m and battery sag correlate: they need room)."""
VAL_BUDGET = 12000
"""Samples of the validation data used to select candidates (at least 120 s, as above)."""
BUDGET_RATE_HZ = 100.0
"""The sample rate the budgets above are counted at: a faster log gets the same time."""
BUDGET_MAX_FACTOR = 5
"""A faster log's budgets grow at most this much (run time grows with them)."""


def _budget(runs: Sequence[Series], samples: int) -> int:
    """``samples`` at :data:`BUDGET_RATE_HZ`, as samples of ``runs`` at their rate."""
    steps = [float(np.median(np.diff(r.t))) for r in runs if len(r) > 1]
    h = float(np.median(steps)) if steps else 1.0 / BUDGET_RATE_HZ
    if not h > 0.0:
        return samples
    per_time = round(samples / (BUDGET_RATE_HZ * h))
    return int(min(max(samples, per_time), BUDGET_MAX_FACTOR * samples))


GAIN_MIN = 0.5
"""Points of validation fit a cause must add to be accepted (the selection's test)."""
MAX_EXTRA_ROUNDS = 2
"""Rounds of trying the remaining candidates on top of the accepted ones."""
SETTLE = 3.0
"""A hill acts on the speed while the truck is on its stretch and for about this many
mechanical time constants after it left: its validation is judged on those samples."""
MIN_SUPPORT = 50
"""Fewest validation samples under a hill's influence to validate it at all."""

SEED_NAMES = ("R_m", "L_m", "K_v", "K_T", "J_S", "K_coulomb", "K_stiction")


@dataclass(frozen=True)
class _Model:
    fit: FitResult
    names: tuple[str, ...]
    val_cost: float


def _quiet(_: str) -> None:
    return None


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


def identify_voltage(
    p0: VehicleParams, runs: Sequence[Series], progress: Progress = _quiet
) -> FitResult:
    """Seed model fitted to all runs of voltage-input logs (no effects); the supply raised
    to the largest command when the configured one is lower (:func:`supply_for`)."""
    p0, supply_note = supply_for(p0, runs)
    if supply_note is not None:
        progress(supply_note)
    whole = merged(runs)
    fit_data = chunks_of_runs(runs, _budget(runs, FIT_BUDGET))
    w = weights_for(fit_data)
    p_lin, _ = _linear_start(p0, runs, progress)
    free = seed_params(p_lin, whole.i is not None)
    grid = stiction_grid(p0, whole)
    ls = least_squares_model(p0, runs)
    best = _fit_seed(p0, p_lin, free, fit_data, w, grid, progress, ls)
    return _restick(best, grid, list(runs), w)


def _linear_start(
    p0: VehicleParams, runs: Sequence[Series], progress: Progress
) -> tuple[VehicleParams, Feedforward | None]:
    p_lin, ff = start_model(p0, runs)
    if ff is None:
        progress("linear estimate: too few sliding samples; starting from the configuration")
    else:
        progress(
            f"linear estimate (SysId form): kS={ff.kS:.4g} V, kV={ff.kV:.4g} V s/m, "
            f"kA={ff.kA:.4g} V s^2/m -> K_v={p_lin.K_v:.4g}, J_S={p_lin.J_S:.4g}, "
            f"K_coulomb={p_lin.K_coulomb:.4g}"
        )
    return p_lin, ff


def _fit_seed(
    p0: VehicleParams,
    p_lin: VehicleParams,
    free: list[Param],
    fit_data: list[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Progress,
    ls: LeastSquares | None = None,
    val_data: list[Series] | None = None,
) -> FitResult:
    """Simulation-error refinement from the linear start ``p_lin`` (and from the
    configuration ``p0``, a second start); the best of the refined models and the
    unrefined linear start and least-squares model ``ls`` (the refinement must beat
    where it started)."""
    progress("fitting the seed model (motor, inertia, Coulomb, stiction)")
    r = residuals(p_lin, Effects(), fit_data, w)
    start = FitResult(p_lin, Effects(), float(r @ r), len(r), 0)
    starts = [start]
    if ls is not None:
        r = residuals(ls.params, Effects(), fit_data, w)
        starts.append(FitResult(ls.params, Effects(), float(r @ r), len(r), 0))
    first = fit_with_stiction(p_lin, Effects(), free, fit_data, w, grid, progress, max_nfev=80)
    fits = [first, *starts]
    # Second start: the configuration, unless the data's machine is far from it (then a
    # start there costs evaluations and finds nothing the data's start does not).
    if not configuration_notes(p_lin, p0):
        alt = p0 if p0 != p_lin else p0.replace(J_S=p0.J_S * 2.0, K_coulomb=p0.K_coulomb * 0.5)
        alt = alt.replace(K_stiction=max(alt.K_stiction, alt.K_coulomb))
        fits.append(
            fit_with_stiction(alt, Effects(), free, fit_data, w, grid, progress, max_nfev=80)
        )
    # Third start: the linear start with its breakaway scanned first.  A stiction far from
    # the configured one made the first fit move Coulomb friction and K_v to absorb it (a
    # local minimum the later scan could not leave: K_coulomb 0.026 for 0.015).
    p_st, _ = scan_stiction(p_lin, Effects(), grid, fit_data, w)
    if p_st.K_stiction != p_lin.K_stiction:
        fits.append(
            fit_with_stiction(p_st, Effects(), free, fit_data, w, grid, progress, max_nfev=80)
        )
    best = min(fits, key=lambda m: m.sse)
    if val_data is None:
        return best
    # Estimation data that hardly show one constant (slow symmetric ramps and kA) leave
    # fits of nearly equal cost there and far apart elsewhere: when the best one's
    # constants are not all determined (Fisher information), among the fits near the
    # best the validation data choose.
    rel = fisher_rel_se(best, free, fit_data, w)
    if rel is None or max(rel[1:]) < DETERMINED:
        return best
    low = best.sse
    near = [m for m in fits if m.sse <= low + max(NEAR_SSE * low, 2.0 * BIC_MIN)]
    return min(near, key=lambda m: _val_cost(m, val_data, w))


NEAR_SSE = 0.5
"""Seed fits within this fraction of the best estimation cost go to the validation data."""


def _restick(m: FitResult, grid: Sequence[float], data: list[Series], w: Weights) -> FitResult:
    """``m`` with K_stiction re-scanned on ``data`` (the other parameters held)."""
    p, sse = scan_stiction(m.params, m.effects, grid, data, w)
    return dataclasses.replace(m, params=p, sse=sse)


def _val_cost(m: FitResult, val: Sequence[Series], w: Weights) -> float:
    r = residuals(m.params, m.effects, val, w)
    return float(r @ r)


def _delta_bic(new: FitResult, old: FitResult, extra: int) -> float:
    return delta_bic(new.sse, old.sse, old.n, extra)


def _fit_candidate(
    base: FitResult,
    seed_free: list[Param],
    extra_free: list[Param],
    cand: Candidate,
    fit_data: list[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Progress,
    val_data: list[Series] | None = None,
) -> FitResult:
    """Fit ``base`` + one more candidate (grid start, then joint refit).

    A threshold (dead zone) is only known to between the command levels of the fit
    data; among the values those data cannot tell apart, the validation data choose.
    """
    name = cand.param.name
    e_base = dataclasses.replace(base.effects, **dict(cand.preset))
    value, _ = scan(base.params, e_base, name, cand.grid, fit_data, w)
    e0 = dataclasses.replace(e_base, **{name: value})
    free = [*seed_free, *extra_free]
    if cand.smooth:
        own = [cand.param, *cand.extra]
        out = fit_with_stiction(base.params, e0, [*free, *own], fit_data, w, grid, progress)
        if cand.param.name == "hill_force":
            out = _refine_stretch(out, [*free, cand.param], fit_data, w, grid, progress)
    else:
        first = fit_with_stiction(base.params, e0, free, fit_data, w, grid, progress)
        value, _ = scan(first.params, first.effects, name, cand.grid, fit_data, w, coarse=200)
        e1 = dataclasses.replace(first.effects, **{name: value})
        out = fit_with_stiction(first.params, e1, free, fit_data, w, grid, progress)
        if val_data is not None:
            out = _settle_tie(out, name, cand.grid, fit_data, val_data, w)
    if name == "sensor_lag" and base.effects.sensor_lag == 0.0:
        # A lag in the speed sensor looks like inertia: the seed fit (and the linear
        # start) put the lag into J_S.  Second start: most of that time constant as lag.
        p = base.params
        tau = p.J_S * p.R_m / (p.K_T * p.K_v)
        j_lo = min(f.lo for f in seed_free if f.name == "J_S")
        alt = p.replace(J_S=max(0.05 * p.J_S, 1.01 * j_lo))
        e_alt = dataclasses.replace(base.effects, sensor_lag=0.95 * tau)
        second = fit_with_stiction(alt, e_alt, [*free, cand.param], fit_data, w, grid, progress)
        out = second if second.sse < out.sse else out
    # Never worse than without the candidate (a local minimum): then it is simply off.
    return out if out.sse <= base.sse else base


def _params_of(cand: Candidate, e: Effects) -> dict[str, float]:
    """The candidate's fitted parameter and its held ones (a hill's start, length)."""
    out = {cand.param.name: float(getattr(e, cand.param.name))}
    for n, _ in cand.preset:
        out[n] = float(getattr(e, n))
    return out


def _profile_of(cand: Candidate, e: Effects) -> dict[str, float | str] | None:
    """Position description of a position-dependent load (reference section 4)."""
    if cand.param.name == "load_force_amplitude":
        return {
            "profile": "rolling",
            "amplitude_n": e.load_force_amplitude,
            "wavelength_m": e.load_force_wavelength,
            "phase_rad": e.load_force_phase,
        }
    if cand.param.name != "hill_force":
        return None
    return {
        "profile": "hill",
        "x_start_m": e.hill_start,
        "x_end_m": e.hill_start + e.hill_length,
        "value": e.hill_force,
    }


def _refine_stretch(
    m: FitResult,
    free: list[Param],
    fit_data: list[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Progress,
) -> FitResult:
    """Move a hill's edges (start, end) by simulation error, force held, then refit.

    The edges only matter through which samples lie on the stretch (the cost is flat
    between them): each edge is scanned on a grid of a few bin widths either side.
    """
    e = m.effects
    step = max(e.hill_length / 10.0, 1e-3)
    best_e, best = e, m.sse
    for _ in range(2):
        for edge in ("start", "end"):
            for k in np.arange(-4.0, 4.5, 1.0) * step:
                start, end = best_e.hill_start, best_e.hill_start + best_e.hill_length
                if edge == "start":
                    start += k
                else:
                    end += k
                if end - start <= step:
                    continue
                trial = dataclasses.replace(best_e, hill_start=start, hill_length=end - start)
                r = residuals(m.params, trial, fit_data, w)
                c = float(r @ r)
                if c < best:
                    best_e, best = trial, c
        step /= 3.0
    if best_e == e:
        return m
    out = fit_with_stiction(m.params, best_e, free, fit_data, w, grid, progress)
    return out if out.sse <= best else dataclasses.replace(m, effects=best_e, sse=best)


def _settle_tie(
    m: FitResult,
    name: str,
    values: Sequence[float],
    fit_data: list[Series],
    val_data: list[Series],
    w: Weights,
) -> FitResult:
    """Among grid values of ``name`` that fit ``fit_data`` equally, the validation-best."""
    costs = {}
    for val in values:
        r = residuals(m.params, dataclasses.replace(m.effects, **{name: float(val)}), fit_data, w)
        costs[float(val)] = float(r @ r)
    low = min(costs.values())
    ties = [v for v, c in costs.items() if c <= low * (1.0 + 1e-9) + 1e-12]
    if len(ties) < 2:
        return m
    best = min(
        ties,
        key=lambda v: _val_cost(
            dataclasses.replace(m, effects=dataclasses.replace(m.effects, **{name: v})),
            val_data,
            w,
        ),
    )
    eff = dataclasses.replace(m.effects, **{name: best})
    return dataclasses.replace(m, effects=eff, sse=costs[best])


def _structured(m: FitResult, runs: Sequence[Series]) -> bool:
    """The free-run speed residual of ``m`` on ``runs`` has structure beyond the noise."""
    y, y_sim = _free_run(m.params, m.effects, runs)
    return _whiteness_of(y - y_sim, runs)[1]


def _free_run(
    p: VehicleParams, e: Effects, runs: Sequence[Series]
) -> tuple[np.ndarray, np.ndarray]:
    """Measured and simulated speed of every run (each from its own start), end to end."""
    sims = [predict(p, e, r).v for r in runs]
    return np.concatenate([r.v for r in runs]), np.concatenate(sims)


def _gain_where_acting(
    new: FitResult, old: FitResult, runs: Sequence[Series], noise: float
) -> float:
    """Points of free-run fit ``new`` gains over ``old`` on the samples of ``runs`` where
    the two differ by more than twice the noise (where the added cause acts; all samples
    when fewer than :data:`MIN_SUPPORT` do): of the speed, or of the current when logged
    (a dead zone may show in the current only), whichever gains more."""
    p_new = [predict(new.params, new.effects, r) for r in runs]
    p_old = [predict(old.params, old.effects, r) for r in runs]
    outputs = [
        (
            np.concatenate([r.v for r in runs]),
            np.concatenate([q.v for q in p_new]),
            np.concatenate([q.v for q in p_old]),
            noise,
        )
    ]
    if all(r.i is not None for r in runs):
        cur = [r.i for r in runs if r.i is not None]
        outputs.append(
            (
                np.concatenate(cur),
                np.concatenate([q.i for q in p_new]),
                np.concatenate([q.i for q in p_old]),
                float(np.mean([noise_std(c) for c in cur])),
            )
        )
    gains = []
    for y, y_new, y_old, sd in outputs:
        acts = np.abs(y_new - y_old) > 2.0 * sd
        if int(acts.sum()) < MIN_SUPPORT:
            acts = np.ones(len(y), dtype=bool)
        gains.append(fit_percent(y[acts], y_new[acts]) - fit_percent(y[acts], y_old[acts]))
    return max(gains)


def _residual_signals(runs: Sequence[Series]) -> dict[str, np.ndarray]:
    """The signals a residual over ``runs`` is compared with (same length, end to end)."""
    sig: dict[str, list[np.ndarray]] = {
        "speed": [],
        "acceleration": [],
        "command_sign": [],
        "time": [],
        "position": [],
    }
    for r in runs:
        sig["speed"].append(r.v)
        sig["acceleration"].append(np.gradient(r.v, r.t) if len(r) > 2 else np.zeros(len(r)))
        sig["command_sign"].append(np.sign(r.inp))
        sig["time"].append(r.t - r.t[0])
        sig["position"].append(r.x if r.x is not None else np.zeros(len(r)))
    return {k: np.concatenate(v) for k, v in sig.items()}


def _whiteness_of(r: np.ndarray, runs: Sequence[Series]) -> tuple[Whiteness, bool]:
    """Whiteness statistics of a residual over ``runs`` and whether it is structured.
    A sampled-and-held speed is judged at its fresh readings only (between them the
    held value is stale by construction, a staircase no model of the truck explains)."""
    whole = merged(runs)
    noise = float(np.mean([noise_std(x.v) for x in runs]))
    fresh = np.concatenate([fresh_mask(x.v) for x in runs])
    r, inp, t = r[fresh], whole.inp[fresh], whole.t[fresh]
    h = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    wt = whiteness(r, inp, noise, max_lag=max(10, round(1.0 / h)))
    return wt, structured(wt, noise, 2e-3 * float(np.std(whole.v)))


def _close(a: float, b: float) -> bool:
    """Two validation costs the data cannot tell apart (:func:`selection.close`)."""
    return close(a, b)


def _rival(
    current: _Model,
    accepted: list[str],
    name: str,
    tried: dict[str, _Model],
    by_name: dict[str, Candidate],
    seed_free: list[Param],
    fit_data: list[Series],
    val_data: list[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Progress,
) -> str | None:
    """The accepted effect that ``name`` can replace equally well, if any.

    Tried only for rivals that explained about as much alone: swap one for the other
    in the current model, refit, and compare the validation costs.
    """
    for a in accepted:
        if not _close(tried[name].val_cost, tried[a].val_cost):
            continue
        progress(f"swap test: {name} instead of {a}")
        off = dataclasses.replace(current.fit.effects, **{by_name[a].param.name: 0.0})
        base = FitResult(current.fit.params, off, float("inf"), current.fit.n, 0)
        extra = [by_name[x].param for x in accepted if x != a and by_name[x].smooth]
        f = _fit_candidate(base, seed_free, extra, by_name[name], fit_data, w, grid, progress)
        if _close(_val_cost(f, val_data, w), current.val_cost):
            return a
    return None


def _hill_support(p: VehicleParams, e: Effects, data: Sequence[Series], w: Weights) -> np.ndarray:
    """Which entries of :func:`residuals` over ``data`` the hill of ``e`` acts on: the
    samples on its stretch and up to :data:`SETTLE` time constants after leaving it."""
    settle = SETTLE * (time_constant(p) or 0.0)
    lo, hi = e.hill_start, e.hill_start + e.hill_length
    parts = []
    for s in data:
        on = np.zeros(len(s), dtype=bool) if s.x is None else (s.x >= lo) & (s.x < hi)
        last = np.maximum.accumulate(np.where(on, s.t, -np.inf))
        near = s.t - last <= settle
        parts.append(near)
        if w.i and s.i is not None:
            parts.append(near[1:])
    return np.concatenate(parts) if parts else np.zeros(0, dtype=bool)


def _hill_val_costs(
    new: FitResult, old: FitResult, hill: Effects, val: Sequence[Series], w: Weights
) -> tuple[float, float] | None:
    """Validation costs of ``new`` and ``old`` where the hill of ``hill`` acts (None: the
    validation data hardly reach its stretch)."""
    mask = _hill_support(new.params, hill, val, w)
    if int(mask.sum()) < MIN_SUPPORT:
        return None
    r_new = residuals(new.params, new.effects, val, w)[mask]
    r_old = residuals(old.params, old.effects, val, w)[mask]
    return float(r_new @ r_new), float(r_old @ r_old)


def _crossings(p: VehicleParams, hill: Effects, runs: Sequence[Series]) -> list[Series]:
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


def _held_out_crossings(
    model: FitResult, hill: Effects, est: Sequence[Series], w: Weights
) -> bool | None:
    """A hill validated on held-out crossings of the estimation runs (when the
    validation data do not reach its stretch): the visits to the stretch in two folds
    (alternate visits), the hill's force fitted on one fold (the rest of ``model``
    held; ``hill`` gives the stretch) must lower the other fold's cost by
    :data:`REL_MIN`, both ways.  None: fewer than two visits."""
    visits = _crossings(model.params, hill, est)
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


def _passes(
    new: _Model, old: _Model, extra: int, hill_ok: bool | None = None
) -> tuple[bool, float]:
    """Whether ``new`` earns its place over ``old`` (:func:`selection.passes`) and the
    change of the information criterion.  When the difference is a hill, ``hill_ok``
    replaces the validation test (a load on a stretch of road changes nothing
    elsewhere: it is validated where it acts)."""
    dbic = _delta_bic(new.fit, old.fit, extra)
    if hill_ok is None:
        return passes(dbic, new.val_cost, old.val_cost), dbic
    return dbic < -BIC_MIN and hill_ok, dbic


def _evidence(m: _Model, base: _Model) -> float:
    """How much better ``m`` explains all the data than ``base`` (lower: better): the
    product of its cost ratios on the fit data and on the validation data.  Either set
    alone can mislead: a short validation chirp can prefer a sensor lag (with a smaller
    inertia) to the dead zone the steps show plainly."""
    fit_ratio = m.fit.sse / base.fit.sse if base.fit.sse > 0.0 else 1.0
    val_ratio = m.val_cost / base.val_cost if base.val_cost > 0.0 else 1.0
    return fit_ratio * val_ratio


def _with_delay(
    tried: dict[str, _Model], base: _Model, skip: Sequence[str], order: Sequence[tuple[str, str]]
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


def _together(
    model: FitResult, causes: Sequence[Candidate], report: Sequence[Series], best: ModelSummary
) -> tuple[list[Finding], list[str], ModelSummary, np.ndarray] | None:
    """All of ``causes`` in ``model``, when they earn their place only together: the model
    with all of them beats ``best`` (what one at a time kept) on the report data, and
    switching any one of them off lowers that fit (its ``fit_gain_percent``: what it adds
    to the others).  A cause fitted jointly with another (the battery's sag with the
    loop's own delay) may be worse alone than none at all; None when they do not."""
    full, y_full = _summary(model.params, model.effects, report)
    if full.fit_percent <= best.fit_percent:
        return None
    found: list[Finding] = []
    for c in causes:
        off = dataclasses.replace(model.effects, **{c.param.name: 0.0})
        gain = full.fit_percent - _summary(model.params, off, report)[0].fit_percent
        if gain <= 0.0:
            return None
        found.append(
            Finding(
                name=c.output or c.name,
                params=_params_of(c, model.effects),
                profile=_profile_of(c, model.effects),
                fit_percent=full.fit_percent,
                fit_gain_percent=gain,
            )
        )
    return found, [c.name for c in causes], full, y_full


def _summary(
    p: VehicleParams, e: Effects, runs: Sequence[Series]
) -> tuple[ModelSummary, np.ndarray]:
    y, y_sim = _free_run(p, e, runs)
    params = {n: float(getattr(p, n)) for n in SEED_NAMES}
    for n in e.active():
        params[n] = float(getattr(e, n))
        for c in COMPANIONS.get(n, ()):
            params[c] = float(getattr(e, c))
    if e.hill_force != 0.0:
        for n in ("hill_force", "hill_start", "hill_length"):
            params[n] = float(getattr(e, n))
    if e.load_force_amplitude != 0.0:
        for n in ("load_force_amplitude", "load_force_wavelength", "load_force_phase"):
            params[n] = float(getattr(e, n))
    ff = feedforward_of(p).to_json()
    # A sampled-and-held speed is compared at its fresh readings (the held ones are stale).
    m = np.concatenate([r.fresh for r in runs])
    summary = ModelSummary(
        fit_percent(y[m], y_sim[m]), rmse(y[m], y_sim[m]), params, feedforward=ff
    )
    return summary, y_sim


def diagnose_voltage(
    p0: VehicleParams,
    runs: Sequence[Series],
    validate: Sequence[Series] | None = None,
    progress: Progress = _quiet,
) -> Diagnosis:
    """Diagnose voltage-input runs (see module docstring); ``validate`` runs when given.
    The supply is raised to the largest command when the configured one is lower
    (:func:`supply_for`, noted)."""
    p0, supply_note = supply_for(p0, [*runs, *(validate or [])])
    if supply_note is not None:
        progress(supply_note)
    runs = [with_position(r) for r in runs]
    validate = [with_position(r) for r in validate] if validate else None
    if validate:
        est, val = list(runs), list(validate)
    else:
        est, val = split_runs_for_validation(runs)
    report = list(validate) if validate else list(runs)
    whole = merged(runs)
    fit_data = chunks_of_runs(est, _budget(est, FIT_BUDGET))
    val_data = chunks_of_runs(val, _budget(val, VAL_BUDGET))
    w = weights_for(fit_data)
    p_lin, ff = _linear_start(p0, est, progress)
    ls = least_squares_model(p0, est)
    seed_free = seed_params(p_lin, whole.i is not None)
    grid = stiction_grid(p0, whole)
    base_fit = _fit_seed(p0, p_lin, seed_free, fit_data, w, grid, progress, ls, val_data)
    base = _Model(base_fit, (), _val_cost(base_fit, val_data, w))
    rejected: list[Rejected] = []

    def possible(m: FitResult, names: Sequence[str]) -> bool:
        """Every effect of ``m`` physically possible; else recorded as rejected."""
        ok = True
        for n in names:
            pn = by_name[n].param.name
            e = m.effects
            if pn == "hill_force":
                why = hill_problem(e.hill_force, e.hill_start, e.hill_length, m.params, runs)
            elif pn == "load_force_amplitude":
                why = rolling_problem(
                    e.load_force_amplitude, e.load_force_wavelength, m.params, runs
                )
            else:
                why = effect_problem(n, float(getattr(m.effects, pn)), m.params, runs, p0)
            if why is not None:
                ok = False
                if all(r.reason != why for r in rejected):
                    rejected.append(Rejected(n, {pn: float(getattr(m.effects, pn))}, why))
        return ok

    def is_hill(name: str) -> bool:
        return by_name[name].param.name == "hill_force"

    noise_val = float(np.mean([noise_std(r.v) for r in val]))

    def earns(name: str, new: _Model, old: _Model) -> bool:
        """``new`` (``old`` + ``name``) raises the validation fit where the cause acts
        by :data:`GAIN_MIN` points (a hill: validated where it acts, :func:`hill_check`)."""
        if is_hill(name):
            return True
        return _gain_where_acting(new.fit, old.fit, val, noise_val) >= GAIN_MIN

    held_out: dict[tuple[float, float, float], bool | None] = {}
    hill_notes: dict[str, str] = {}

    def hill_check(name: str, new: _Model, old: _Model) -> bool | None:
        """The validation of the hill of ``new`` when ``name`` is the hill (else None):
        ``new`` lowers the validation cost where the hill acts by :data:`REL_MIN` (and
        raises it nowhere); when the validation data do not reach the stretch, its
        held-out crossings decide."""
        if not is_hill(name):
            return None
        if new.val_cost > old.val_cost:
            hill_notes[name] = "raises the validation cost"
            return False  # the hill acts nowhere else: a worse validation is the rest's
        e = new.fit.effects
        costs = _hill_val_costs(new.fit, old.fit, e, val_data, w)
        if costs is not None:
            return costs[0] < (1.0 - REL_MIN) * costs[1]
        key = (e.hill_force, e.hill_start, e.hill_length)
        if key not in held_out:
            held_out[key] = _held_out_crossings(new.fit, e, est, w)
        if held_out[key] is None:
            hill_notes[name] = "not validated: no held-out data reach the stretch twice"
            return False
        return held_out[key]

    cands = voltage_candidates(base_fit.params, whole)
    stretch = locate(base_fit.params, runs)
    if stretch is not None:
        progress(
            f"residual localised on [{stretch.start:.3g}, {stretch.start + stretch.length:.3g}]"
            f" m ({stretch.force:.3g} N): hill candidate"
        )
        cands.append(hill_candidate(base_fit.params, stretch))
    wave = locate_wave(base_fit.params, runs)
    if wave is not None:
        progress(f"residual periodic in position ({wave.wavelength:.3g} m): rolling candidate")
        cands.append(rolling_candidate(base_fit.params, wave))
    by_name = {c.name: c for c in cands}
    tried: dict[str, _Model] = {}
    rows: dict[str, CandidateRow] = {}
    base_fit_pct = _summary(base_fit.params, base_fit.effects, val)[0].fit_percent
    for k, cand in enumerate(cands):
        progress(f"candidate {k + 1}/{len(cands)}: {cand.name}")
        f = _fit_candidate(base_fit, seed_free, [], cand, fit_data, w, grid, progress, val_data)
        m = _Model(f, (cand.name,), _val_cost(f, val_data, w))
        ok, dbic = _passes(m, base, 1, hill_check(cand.name, m, base))
        ok = ok and earns(cand.name, m, base)
        note = "passes alone" if ok else hill_notes.get(cand.name, "")
        if ok and not possible(f, [cand.name]):
            ok = False
            note = f"physically impossible: {rejected[-1].reason}"
        tried[cand.name] = m
        fp = _summary(f.params, f.effects, val)[0].fit_percent
        rows[cand.name] = CandidateRow(
            name=cand.name,
            params=_params_of(cand, f.effects),
            fit_percent=fp,
            gain_percent=fp - base_fit_pct,
            cost_ratio=m.val_cost / base.val_cost if base.val_cost > 0 else 1.0,
            delta_bic=dbic,
            accepted=False,
            note=note,
        )
    passing = sorted(
        (n for n, r in rows.items() if r.note == "passes alone"),
        key=lambda n: _evidence(tried[n], base),
    )
    current = base
    accepted: list[str] = []
    ambiguous: list[tuple[str, str]] = []
    for name in passing:
        cand = by_name[name]
        if not accepted:
            new = tried[name]
        else:
            progress(f"joint refit: {', '.join(accepted)} + {name}")
            extra = [by_name[a].param for a in accepted if by_name[a].smooth]
            f = _fit_candidate(
                current.fit, seed_free, extra, cand, fit_data, w, grid, progress, val_data
            )
            new = _Model(f, (*current.names, name), _val_cost(f, val_data, w))
        ok, _ = _passes(new, current, 1, hill_check(name, new, current))
        ok = ok and earns(name, new, current)
        if ok and possible(new.fit, [*accepted, name]):
            accepted.append(name)
            current = new
            rows[name] = dataclasses.replace(rows[name], accepted=True, note="accepted")
            continue
        rival = _rival(
            current,
            accepted,
            name,
            tried,
            by_name,
            seed_free,
            fit_data,
            val_data,
            w,
            grid,
            progress,
        )
        if rival is not None:
            ambiguous.append((rival, name))
            rows[name] = dataclasses.replace(rows[name], note=f"ambiguous with {rival}")
        else:
            rows[name] = dataclasses.replace(rows[name], note="adds nothing once others are in")

    # A weaker effect can be masked by a stronger one when tried alone: while the
    # validation residual still has structure, try the rest on top of the current model.
    for _ in range(MAX_EXTRA_ROUNDS):
        if not accepted or not _structured(current.fit, val):
            break
        taken = set(accepted) | {b for _, b in ambiguous}
        rest = [c for c in cands if c.name not in taken]
        extra = [by_name[a].param for a in accepted if by_name[a].smooth]
        best: _Model | None = None
        for cand in rest:
            progress(f"structure remains: trying {cand.name} on top of {', '.join(accepted)}")
            f = _fit_candidate(
                current.fit, seed_free, extra, cand, fit_data, w, grid, progress, val_data
            )
            new = _Model(f, (*current.names, cand.name), _val_cost(f, val_data, w))
            if (
                _passes(new, current, 1, hill_check(cand.name, new, current))[0]
                and earns(cand.name, new, current)
                and possible(new.fit, new.names)
                and (best is None or new.val_cost < best.val_cost)
            ):
                best = new
        if best is None:
            break
        name = best.names[-1]
        accepted.append(name)
        current = best
        rows[name] = dataclasses.replace(
            rows[name], accepted=True, note="accepted on top of the others"
        )

    # Pairs of causes, when one is not enough (truckd/ident/pairs.py): each member
    # must earn its place against the other alone, the pair against the greedy model.
    if len(accepted) < 2:

        def fit_pair(a: str, b: str) -> _Model | None:
            progress(f"pair: {a} + {b}")
            ca = by_name[a]
            own = [ca.param, *ca.extra] if ca.smooth else []
            f = _fit_candidate(
                tried[a].fit, seed_free, own, by_name[b], fit_data, w, grid, progress, val_data
            )
            m = _Model(f, (a, b), _val_cost(f, val_data, w))
            return m if possible(m.fit, [a, b]) else None

        def member_earns(m: _Model, name: str) -> bool:
            other = tried[m.names[1] if name == m.names[0] else m.names[0]]
            ok = _passes(m, other, 1, hill_check(name, m, other))[0]
            return ok and earns(name, m, other)

        single = {n: m.val_cost for n, m in tried.items()}
        impossible = [n for n, r in rows.items() if r.note.startswith("physically impossible")]
        order = pair_order(single, base.val_cost, skip=impossible, accepted=accepted)
        order += _with_delay(tried, base, impossible, order)
        pair = best_pair(order, current.val_cost, fit_pair, lambda m: m.val_cost, member_earns)
        if pair is not None:
            for n in accepted:
                if n not in pair.names:
                    rows[n] = dataclasses.replace(
                        rows[n], accepted=False, note="replaced by a pair of causes"
                    )
            for n in pair.names:
                other = pair.names[1] if n == pair.names[0] else pair.names[0]
                rows[n] = dataclasses.replace(
                    rows[n], accepted=True, note=f"accepted with {other} (a pair)"
                )
            accepted, current = list(pair.names), pair

    # Backward check: an effect accepted early may be redundant once later ones are in.
    if len(accepted) > 1:
        for name in list(accepted):
            others = [a for a in accepted if a != name]
            progress(f"backward check: {', '.join(others)} without {name}")
            off = dataclasses.replace(current.fit.effects, **{by_name[name].param.name: 0.0})
            base_wo = FitResult(current.fit.params, off, float("inf"), current.fit.n, 0)
            extra = [by_name[a].param for a in others if by_name[a].smooth]
            f = fit_with_stiction(
                base_wo.params, off, [*seed_free, *extra], fit_data, w, grid, progress
            )
            reduced = _Model(f, tuple(others), _val_cost(f, val_data, w))
            ok_hill = hill_check(name, current, reduced)
            if not _passes(current, reduced, 1, ok_hill)[0]:
                accepted.remove(name)
                current = reduced
                rows[name] = dataclasses.replace(
                    rows[name], accepted=False, note="redundant once the others are in"
                )

    # Final joint refit of the extended model on more of the data; stiction shows only
    # at the breakaways, which chunks may miss: a last look at it on all the data.
    fit_runs = est if validate else list(runs)  # selection done: use all the data
    polish_data = chunks_of_runs(fit_runs, _budget(fit_runs, FINAL_BUDGET), pieces=8)
    base_pol = _restick(base_fit, grid, fit_runs, w)
    final = base_pol
    if accepted:
        progress("final joint refit on more data")
        extra = [by_name[a].param for a in accepted if by_name[a].smooth]
        final = fit_with_stiction(
            current.fit.params,
            current.fit.effects,
            [*seed_free, *extra],
            polish_data,
            weights_for(polish_data),
            grid,
            progress,
            max_nfev=FINAL_NFEV,
        )
        final = _restick(final, grid, fit_runs, w)
        if effects_problems(final.effects, final.params, runs, p0):
            final = _restick(current.fit, grid, fit_runs, w)  # the refit left the limits
    base_sum, y_base = _summary(base_pol.params, base_pol.effects, report)

    def keep(model: FitResult) -> tuple[list[Finding], list[str], ModelSummary, np.ndarray]:
        """The accepted causes that earn their place in ``model`` on the report data,
        in order: each must raise the report fit by :data:`GAIN_MIN` points (a hill, on
        its stretch only, validated where it acts: by any gain)."""
        found: list[Finding] = []
        kept_: list[str] = []
        y_e, e_sum = y_base, base_sum
        for name in accepted:
            later = {by_name[a].param.name: 0.0 for a in accepted if a not in (*kept_, name)}
            trial = dataclasses.replace(model.effects, **later)
            s_k, y_k = _summary(model.params, trial, report)
            if s_k.fit_percent <= e_sum.fit_percent:
                continue
            found.append(
                Finding(
                    name=by_name[name].output or name,
                    params=_params_of(by_name[name], model.effects),
                    profile=_profile_of(by_name[name], model.effects),
                    fit_percent=s_k.fit_percent,
                    fit_gain_percent=s_k.fit_percent - e_sum.fit_percent,
                )
            )
            kept_.append(name)
            e_sum, y_e = s_k, y_k
        if len(kept_) < len(accepted) > 1:  # causes that act together (a pair)
            together = _together(model, [by_name[a] for a in accepted], report, e_sum)
            if together is not None:
                return together
        return found, kept_, e_sum, y_e

    # Never worse: each accepted cause must raise the report fit; one that does not is
    # switched off (a cause that lowers the validation fit is no cause).  The final
    # joint refit never drops a cause that earned its place in the selection's model:
    # when it would, the selection's model stays.
    findings, kept, ext_sum, y_ext = keep(final)
    if accepted and final is not current.fit:
        sel = _restick(current.fit, grid, fit_runs, w)
        alt = keep(sel)
        if len(alt[1]) > len(kept) or (
            len(alt[1]) == len(kept) and alt[2].fit_percent > ext_sum.fit_percent
        ):
            progress("the final joint refit loses a cause: the selection's model stays")
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
    switched_off = {by_name[a].param.name: 0.0 for a in accepted if a not in kept}
    ext_params = final.params if kept else base_pol.params
    ext_effects = dataclasses.replace(final.effects, **switched_off) if kept else base_pol.effects
    fisher = fisher_rel_se(base_fit, seed_free, fit_data, w)
    notes = [*_notes(runs, ff, fisher)]
    ls_json: dict[str, float | None] | None = None
    if ls is not None:
        ls_sum, y_ls = _summary(ls.params, Effects(), report)
        ls_json = _least_squares_json(ls, ls_sum.fit_percent)
        progress(f"least squares (SysId's model): fit {ls_sum.fit_percent:.2f} %")
        if ext_sum.fit_percent < ls_sum.fit_percent:
            notes.append(
                f"the simulation-error fit ({ext_sum.fit_percent:.1f} %) does not beat the "
                f"data's own least-squares model ({ls_sum.fit_percent:.1f} %) on the "
                "validation data: the extended model is the least-squares model"
            )
            for name in kept:
                rows[name] = dataclasses.replace(
                    rows[name], accepted=False, note="below least squares: not accepted"
                )
            findings, kept = [], []
            ext_sum, y_ext = ls_sum, y_ls
            ext_params, ext_effects = ls.params, Effects()
    binding = _binding_limits(
        ext_params,
        ext_effects,
        [*seed_free, *[by_name[a].param for a in kept]],
        polish_data,
        report,
        grid,
        progress,
    )
    notes.extend(binding)
    machine = configuration_notes(ext_params, p0)
    notes.extend(machine)
    alerts = [n for n in notes if n.startswith("the simulation-error fit")]
    alerts.extend([*binding, *machine])
    notes.extend(vehicle_problems(ext_params, runs))
    y_all = np.concatenate([r.v for r in report])
    wt, unexplained = _whiteness_of(y_all - y_ext, report)
    rep = merged(report)
    looks = looks_like(y_all - y_ext, _residual_signals(report))
    if unexplained:
        what = (
            ", ".join(f"{k} (r = {c:+.2f})" for k, c in looks.items())
            if looks
            else "none of speed, acceleration, the command's sign, time or position"
        )
        line = (
            f"unexplained: the best model leaves structure in the residual (autocorrelation "
            f"{wt.acf_outside:.0%} and cross-correlation with the input {wt.ccf_outside:.0%} "
            f"of lags outside the band, RMS {wt.rms:.3g} against noise {wt.noise:.3g} m/s); "
            f"it correlates with {what}"
        )
        notes.append(line)
        alerts.append(line)
    if supply_note is not None:
        notes.insert(0, supply_note)
    return Diagnosis(
        input="voltage",
        samples=sum(len(r) for r in runs),
        baseline=base_sum,
        effects=findings,
        extended=ext_sum,
        unexplained=unexplained,
        ambiguous=ambiguous,
        candidates=[rows[c.name] for c in cands],
        notes=notes,
        traces=Traces(
            t=rep.t,
            inp=rep.inp,
            y=rep.v,
            y_base=y_base,
            y_ext=y_ext,
            i=rep.i,
            x=rep.x,
        ),
        vehicle=ext_params,
        model_effects=ext_effects,
        residual_stats={
            "rms": wt.rms,
            "noise": wt.noise,
            "structure": wt.structure,
            "acf_outside_fraction": wt.acf_outside,
            "ccf_outside_fraction": wt.ccf_outside,
            **{f"corr_{k}": c for k, c in looks.items()},
        },
        rejected=rejected,
        linear=None if ff is None else ff.to_json(),
        least_squares=ls_json,
        alerts=alerts,
        runs=len(runs),
        explains=not unexplained and white(wt),
    )


def _least_squares_json(ls: LeastSquares, fit_pct: float) -> dict[str, float | None]:
    """The ``least_squares`` object of the JSON (reference section 4)."""
    se = ls.se
    out: dict[str, float | None] = {"kS": ls.ff.kS, "kV": ls.ff.kV, "kA": ls.ff.kA}
    for k, e in zip(("kS", "kV", "kA"), se, strict=True):
        out[f"{k}_se"] = float(e) if np.isfinite(e) else None
    out["fit_percent"] = float(fit_pct)
    return out


def _value_of(p: VehicleParams, e: Effects, name: str) -> float:
    """A free parameter's value in a model (vehicle parameter or effect)."""
    return float(getattr(p, name)) if hasattr(p, name) else float(getattr(e, name))


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
        val = _value_of(p, e, f.name)
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
        with_pct = _summary(p, e, report)[0].fit_percent
        without = _summary(refit.params, refit.effects, report)[0].fit_percent
        new_val = _value_of(refit.params, refit.effects, f.name)
        out.append(
            f"limit binds: {f.name} = {val:.3g} ends on its {'lower' if at_lo else 'upper'} "
            f"limit {bound:.3g}; fit {with_pct:.1f} % with the limit, {without:.1f} % "
            f"without it ({f.name} = {new_val:.3g})"
        )
    return out


DETERMINED = 0.1
"""A constant of the linear estimate is called determined when its relative standard
error is below this."""


def fisher_rel_se(
    m: FitResult, free: Sequence[Param], data: list[Series], w: Weights
) -> tuple[float, float, float] | None:
    """Relative standard errors of (kS, kV, kA) of the simulation-error fit ``m`` on
    ``data``, from the Fisher information (Gauss-Newton, finite differences in log
    space), the residual's variance, and its lag-1 autocorrelation to count effectively
    independent samples (an autocorrelated residual carries less information).  None
    when the seed's ``K_v``, ``J_S`` or ``K_coulomb`` is not free."""
    names = [f.name for f in free]
    if not {"K_v", "J_S", "K_coulomb"} <= set(names):
        return None
    r0 = residuals(m.params, m.effects, data, w)
    cols = []
    step = 1e-3
    for f in free:
        val = _value_of(m.params, m.effects, f.name)
        if f.name == "K_coulomb" and val <= 0.0:
            val = 1e-3 * f.scale
        th = theta_of(m.params, m.effects, free)
        k = names.index(f.name)
        th_up = th.copy()
        th_up[k] = val * (1.0 + step) / f.scale
        p_up, e_up = apply(m.params, m.effects, free, th_up)
        r_up = residuals(p_up, e_up, data, w)
        cols.append((r_up - r0) / step)  # per unit relative change (log space)
    jac = np.column_stack(cols)
    n = len(r0)
    if n <= len(free):
        return None
    res = r0 - np.mean(r0)
    rho = float(res[:-1] @ res[1:]) / max(float(res @ res), 1e-300)
    rho = min(max(rho, 0.0), 0.99)
    var = float(r0 @ r0) / (n - len(free)) * (1.0 + rho) / (1.0 - rho)
    try:
        cov = var * np.linalg.pinv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return None
    kv, js, kc = names.index("K_v"), names.index("J_S"), names.index("K_coulomb")
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # kA = R_m J_S / (K_T ratio) with K_T tied to K_v: log kA = log J_S - log K_v + c.
    ka = float(np.sqrt(max(cov[js, js] + cov[kv, kv] - 2.0 * cov[js, kv], 0.0)))
    ks = float(np.sqrt(max(cov[kc, kc] + cov[kv, kv] - 2.0 * cov[kc, kv], 0.0)))
    if m.params.K_coulomb <= 0.0:
        ks = float("inf")
    return ks, float(d[kv]), ka


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
