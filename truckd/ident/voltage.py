"""Simulation-error fitting of the voltage-input model (seed + effects).

Free parameters are scaled (``theta = value / scale``) and bounded; starting points and
bounds come from the configuration's vehicle.  What the data can determine:

* ``t, u, v`` only: the first-order model's coefficients fix ``K_v``, ``J_S R_m/K_T``,
  ``K_coulomb R_m/K_T`` and ``K_stiction R_m/K_T``.  ``R_m`` stays at the configured
  value and ``K_T/K_v`` at the configured ratio; ``L_m`` is never identifiable from
  speed sampled far slower than ``L_m/R_m`` (< 1 ms) and keeps its configured value.
  Viscous friction cannot be told from ``K_v`` (both only scale the speed per volt), so
  it is not a candidate without current.
* with ``i``: the quasi-static current ``(V - K_v omega)/R`` adds ``R_m`` and separates
  ``K_v`` from viscous friction; ``K_T`` still only appears as ``J_S/K_T`` etc.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from truckd.ident.data import Series, noise_std
from truckd.ident.fastsim import predict as predict  # the free run of one series
from truckd.ident.prediction import StictionBand, VoltagePrediction
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]

SEED_ROOM = 1000.0
"""The seed's smooth parameters may move this factor either way from their start (the
data's own least-squares model): wide enough that the data, not the configuration,
decide how big the machine is; a fit that still ends on one is reported as binding."""
VEHICLE_FREE = ("K_v", "J_S", "K_coulomb", "stiction_excess", "R_m")
"""Names of the seed parameters the fit may free (``stiction_excess`` = Ks - Kc)."""


@dataclass(frozen=True)
class Param:
    """A free parameter: value = ``theta * scale``, bounded to ``[lo, hi]`` (SI)."""

    name: str
    scale: float
    lo: float
    hi: float


@dataclass(frozen=True)
class Weights:
    """Residual weights: 1/noise level of speed (s/m) and current (1/A, 0 = unused)."""

    v: float
    i: float = 0.0


def seed_params(p0: VehicleParams, with_current: bool) -> list[Param]:
    """The seed's smooth free parameters with bounds around the starting values ``p0``
    (the linear estimate from the data, :func:`truckd.ident.linear.start_model`).

    Stiction is not among them: it only decides *which* commands break the truck
    away, so the cost is flat between command levels; :func:`fit_seed_model` locates
    it on a grid (:func:`stiction_grid`).
    """
    kc = max(p0.K_coulomb, 1e-3 * p0.K_T * p0.V_batt / p0.R_m)
    out = [
        Param("K_v", p0.K_v, p0.K_v / SEED_ROOM, SEED_ROOM * p0.K_v),
        Param("J_S", p0.J_S, p0.J_S / SEED_ROOM, SEED_ROOM * p0.J_S),
        Param("K_coulomb", kc, 0.0, SEED_ROOM * kc),
    ]
    if with_current:
        out.append(Param("R_m", p0.R_m, p0.R_m / SEED_ROOM, SEED_ROOM * p0.R_m))
    return out


def apply(
    p0: VehicleParams, e0: Effects, free: Sequence[Param], theta: Sequence[float] | Array
) -> tuple[VehicleParams, Effects]:
    """The model with the free parameters set from ``theta``."""
    vals = {f.name: float(th) * f.scale for f, th in zip(free, theta, strict=True)}
    veh: dict[str, float] = {}
    if "K_v" in vals:
        veh["K_v"] = vals["K_v"]
        veh["K_T"] = p0.K_T * vals["K_v"] / p0.K_v
    for n in ("J_S", "R_m", "K_coulomb"):
        if n in vals:
            veh[n] = vals[n]
    kc = veh.get("K_coulomb", p0.K_coulomb)
    excess = vals.get("stiction_excess", p0.K_stiction - p0.K_coulomb)
    veh["K_stiction"] = kc + max(excess, 0.0)
    p = p0.replace(**veh)
    eff_vals = {n: v for n, v in vals.items() if n not in VEHICLE_FREE}
    eff = dataclasses.replace(e0, **eff_vals) if eff_vals else e0
    return p, eff


def theta_of(p: VehicleParams, e: Effects, free: Sequence[Param]) -> Array:
    """Scaled values of the free parameters of a model (inverse of :func:`apply`)."""
    out = []
    for f in free:
        if f.name == "stiction_excess":
            val = p.K_stiction - p.K_coulomb
        elif f.name in VEHICLE_FREE:
            val = float(getattr(p, f.name))
        else:
            val = float(getattr(e, f.name))
        out.append(min(max(val, f.lo), f.hi) / f.scale)
    return np.array(out)


def weights_for(data: Sequence[Series]) -> Weights:
    """Weights from the measured noise levels (with floors for noise-free logs)."""
    v = np.concatenate([s.v for s in data])
    sv = max(float(np.mean([noise_std(s.v) for s in data])), 2e-3 * float(np.std(v)), 1e-6)
    if all(s.i is not None for s in data):
        i = np.concatenate([s.i for s in data if s.i is not None])
        si = max(
            float(np.mean([noise_std(s.i) for s in data if s.i is not None])),
            1e-2 * float(np.std(i)),
            1e-6,
        )
        return Weights(v=1.0 / sv, i=1.0 / si)
    return Weights(v=1.0 / sv)


def value_of(p: VehicleParams, e: Effects, name: str) -> float:
    """A free parameter's value in a model (vehicle parameter or effect)."""
    return float(getattr(p, name)) if hasattr(p, name) else float(getattr(e, name))


def restick(m: FitResult, grid: Sequence[float], data: list[Series], w: Weights) -> FitResult:
    """``m`` with K_stiction re-scanned on ``data`` (the other parameters held)."""
    p, sse = scan_stiction(m.params, m.effects, grid, data, w)
    return dataclasses.replace(m, params=p, sse=sse)


def residuals(p: VehicleParams, e: Effects, data: Sequence[Series], w: Weights) -> Array:
    """Weighted free-run residuals (speed, then current when weighted) of all chunks."""
    parts: list[Array] = []
    for s in data:
        parts.extend(_chunk_residuals(s, predict(p, e, s), w))
    return _joined(parts)


def _chunk_residuals(s: Series, pred: VoltagePrediction, w: Weights) -> list[Array]:
    """The weighted residuals of one chunk's free run ``pred`` (speed, then current)."""
    dv = (s.v - pred.v) * w.v
    out = [dv if s.all_fresh else dv[s.fresh]]  # a held speed: fresh readings
    if w.i and s.i is not None:
        out.append((s.i[1:] - pred.i[1:]) * w.i)
    return out


def _joined(parts: Sequence[Array]) -> Array:
    """The chunks' residuals as one vector, a non-finite one scored as a large miss."""
    r = np.concatenate(parts)
    return np.where(np.isfinite(r), r, 1e6)


def speed_fit(p: VehicleParams, e: Effects, s: Series) -> tuple[float, float, Array]:
    """``(fit_percent, rmse (m/s), simulated speed)`` of a free run over ``s``."""
    pred = predict(p, e, s)
    return fit_percent(s.v, pred.v), rmse(s.v, pred.v), pred.v


def fit_percent(y: Array, y_sim: Array) -> float:
    """``100 (1 - ||y - y_sim|| / ||y - mean(y)||)`` (reference section 4)."""
    den = float(np.linalg.norm(y - np.mean(y)))
    if den == 0.0:
        return 0.0
    return 100.0 * (1.0 - float(np.linalg.norm(y - y_sim)) / den)


def rmse(y: Array, y_sim: Array) -> float:
    """Root mean square of ``y - y_sim``."""
    return float(np.sqrt(np.mean((y - y_sim) ** 2)))


@dataclass(frozen=True)
class FitResult:
    """A fitted model and its weighted sum of squared residuals on the fit data."""

    params: VehicleParams
    effects: Effects
    sse: float
    n: int
    nfev: int


def fit(
    p0: VehicleParams,
    e0: Effects,
    free: Sequence[Param],
    data: Sequence[Series],
    w: Weights,
    max_nfev: int = 60,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Least-squares simulation-error fit of the free parameters from ``(p0, e0)``."""
    lo = np.array([f.lo / f.scale for f in free])
    hi = np.array([f.hi / f.scale for f in free])
    x0 = np.clip(theta_of(p0, e0, free), lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))

    def fun(th: Array) -> Array:
        p, e = apply(p0, e0, free, th)
        return residuals(p, e, data, w)

    if free:
        sol = least_squares(
            fun,
            x0,
            bounds=(lo, hi),
            diff_step=1e-3,
            x_scale=1.0,
            ftol=1e-6,
            xtol=1e-6,
            max_nfev=max_nfev,
            method="trf",
        )
        # sol.fun: the residuals at sol.x, as fun computed them (not simulated again)
        th, nfev, r = sol.x, int(sol.nfev), np.asarray(sol.fun, float)
    else:
        th, nfev, r = x0, 0, None
    p, e = apply(p0, e0, free, th)
    if r is None:
        r = residuals(p, e, data, w)
    if progress is not None:
        progress(f"  fit {[f.name for f in free]}: {nfev} evaluations, sse {float(r @ r):.4g}")
    return FitResult(p, e, float(r @ r), len(r), nfev)


def _coarse_then_fine(
    g: Sequence[float], cost: Callable[[float], float], coarse: int, fine: int
) -> None:
    """Evaluate ``cost`` on a sorted grid: at most ``coarse`` evenly spread points, then up
    to ``fine`` points between the best one's coarse neighbours (the caller keeps the costs).
    """
    idx = np.unique(np.linspace(0, len(g) - 1, min(coarse, len(g))).round().astype(int))
    costs = [cost(g[k]) for k in idx]
    j = int(np.argmin(costs))
    lo = int(idx[max(j - 1, 0)])
    hi = int(idx[min(j + 1, len(idx) - 1)])
    for k in np.unique(np.linspace(lo, hi, min(fine, hi - lo + 1)).round().astype(int)):
        cost(g[k])


def same_runs(name: str, data: Sequence[Series]) -> Callable[[float], int] | None:
    """For an effect parameter whose values can give the same free runs of ``data``: the
    key two such values share (None: every value is run).  The dead zone's threshold
    enters a run only where the driver zeroes a command below it
    (:func:`truckd.model.effects.driver_output`): two thresholds that zero the same
    commands, history included, give the same runs bit for bit; the key is how many
    command magnitudes lie below the threshold.  The commands of the run a stretch was cut
    from count too: a winding's heating over it sets the stretch's start."""
    if name != "dead_zone":
        return None
    parts = [
        x
        for s in data
        for x in (s.hist_inp, s.inp, None if s.origin is None else s.origin.inp)
        if x is not None
    ]
    mags = np.sort(np.abs(np.concatenate(parts))) if parts else np.zeros(0)
    return lambda v: int(np.searchsorted(mags, v, side="left"))


def value_cost(
    p: VehicleParams, e: Effects, name: str, data: Sequence[Series], w: Weights
) -> Callable[[float], float]:
    """The weighted sum of squared residuals of ``data`` with the effect parameter ``name``
    at a value, the rest held; values that give the same runs (:func:`same_runs`) are
    simulated once."""
    key = same_runs(name, data)
    done: dict[float | int, float] = {}

    def cost(val: float) -> float:
        k = float(val) if key is None else key(float(val))
        if k not in done:
            r = residuals(p, dataclasses.replace(e, **{name: float(val)}), data, w)
            done[k] = float(r @ r)
        return done[k]

    return cost


def scan(
    p: VehicleParams,
    e: Effects,
    name: str,
    values: Sequence[float],
    data: Sequence[Series],
    w: Weights,
    coarse: int = 30,
    fine: int = 16,
) -> tuple[float, float]:
    """Best value of one effect parameter on a sorted grid, the rest held: (value, sse).

    Long grids: a coarse pass over ``coarse`` points, then up to ``fine`` points between
    the best one's coarse neighbours.
    """
    cache: dict[float, float] = {}
    run_cost = value_cost(p, e, name, data, w)

    def cost(val: float) -> float:
        if val not in cache:
            cache[val] = run_cost(val)
        return cache[val]

    g = [float(v) for v in values]
    if not g:
        return float(getattr(e, name)), float("inf")
    _coarse_then_fine(g, cost, coarse, fine)
    best = min(cache, key=lambda v: cache[v])
    return best, cache[best]


def stiction_grid(p0: VehicleParams, data: Series) -> tuple[float, ...]:
    """Breakaway voltages (V) between the log's command levels, up to half V_batt.

    Sorted; 0 stands for "no stiction beyond Coulomb" (``K_stiction = K_coulomb``).
    :func:`scan_stiction` turns them into torques with the model's own ``K_T/R_m``.
    """
    u = np.abs(data.inp)
    levels = np.unique(np.round(u[(u > 0) & (u < 0.5 * p0.V_batt)], 6))
    mids = 0.5 * (levels[1:] + levels[:-1]) if len(levels) > 1 else levels
    return (0.0, *(float(m) for m in mids))


def scan_stiction(
    p: VehicleParams,
    e: Effects,
    grid: Sequence[float],
    data: Sequence[Series],
    w: Weights,
    coarse: int = 30,
    fine: int = 12,
) -> tuple[VehicleParams, float]:
    """Best K_stiction (>= K_coulomb) on a sorted grid of breakaway voltages (V), the
    rest held: (model, sse).

    A coarse pass over at most ``coarse`` grid points, then up to ``fine`` grid points
    between the best one's coarse neighbours.
    """
    cache: dict[float, float] = {}
    # Per chunk, the sse of the runs simulated so far with the stiction torques that give
    # each one exactly (a chunk that never stops is the same run for every K_stiction);
    # the sums, not the residuals: a long log's residuals for every band would not fit.
    seen: list[list[tuple[StictionBand, float]]] = [[] for _ in data]

    def cost(ks: float) -> float:
        ks = max(float(ks), p.K_coulomb)
        if ks not in cache:
            q = p.replace(K_stiction=ks)
            total = 0.0
            for s, runs in zip(data, seen, strict=True):
                same = next((c for band, c in runs if band.holds(ks)), None)
                if same is None:
                    pred = predict(q, e, s)
                    r = _joined(_chunk_residuals(s, pred, w))
                    same = float(r @ r)
                    if pred.stiction is not None:
                        runs.append((pred.stiction, same))
                total += same
            cache[ks] = total
        return cache[ks]

    _coarse_then_fine([float(v) * (p.K_T / p.R_m) for v in grid], cost, coarse, fine)
    cost(p.K_stiction)
    low = min(cache.values())
    # Where the data cannot tell (no command level in between), keep the value closest
    # to the starting one (from the configuration) rather than an end of the interval.
    ties = [ks for ks, c in cache.items() if c <= low * (1.0 + 1e-9) + 1e-12]
    best = min(ties, key=lambda ks: abs(ks - p.K_stiction))
    return p.replace(K_stiction=best), cache[best]


def fit_with_stiction(
    p0: VehicleParams,
    e0: Effects,
    free: Sequence[Param],
    data: Sequence[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Callable[[str], None] | None = None,
    max_nfev: int = 60,
) -> FitResult:
    """Smooth parameters by least squares, stiction on its grid, then a joint polish."""
    first = fit(p0, e0, free, data, w, max_nfev=max_nfev, progress=progress)
    p1, sse1 = scan_stiction(first.params, first.effects, grid, data, w)
    if p1.K_stiction == first.params.K_stiction or sse1 >= first.sse:
        return first
    return fit(p1, first.effects, free, data, w, max_nfev=max_nfev, progress=progress)
