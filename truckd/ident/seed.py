"""Stage 3 of the diagnosis (:mod:`truckd.ident.diagnose`): the seed model.

The seed (motor, inertia, Coulomb, stiction; no effects) fitted by simulation error on
the estimation data from the least-squares stage's starts (and the configuration),
and how well the data determine its constants (Fisher information).  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.data import (
    Series,
)
from truckd.ident.fanout import Mapper, fan_out, in_order
from truckd.ident.linear import (
    LeastSquares,
    LinearStart,
)
from truckd.ident.physics import (
    configuration_notes,
)
from truckd.ident.runs import Prepared
from truckd.ident.scoring import Model, Progress, val_cost
from truckd.ident.selection import (
    BIC_MIN,
)
from truckd.ident.voltage import (
    FitResult,
    Param,
    Weights,
    apply,
    fit_with_stiction,
    residuals,
    scan_stiction,
    seed_params,
    stiction_grid,
    theta_of,
    value_of,
)
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def fit_seed(
    p0: VehicleParams,
    p_lin: VehicleParams,
    free: list[Param],
    fit_data: list[Series],
    w: Weights,
    grid: Sequence[float],
    progress: Progress,
    ls: LeastSquares | None = None,
    val_data: list[Series] | None = None,
    mapper: Mapper = in_order,
) -> FitResult:
    """Simulation-error refinement from the linear start ``p_lin`` (and from the
    configuration ``p0``, a second start); the best of the refined models and the
    unrefined linear start and least-squares model ``ls`` (the refinement must beat
    where it started).  The refinements run through ``mapper`` (:mod:`truckd.ident.fanout`)."""
    progress("fitting the seed model (motor, inertia, Coulomb, stiction)")
    r = residuals(p_lin, Effects(), fit_data, w)
    start = FitResult(p_lin, Effects(), float(r @ r), len(r), 0)
    starts = [start]
    if ls is not None:
        r = residuals(ls.params, Effects(), fit_data, w)
        starts.append(FitResult(ls.params, Effects(), float(r @ r), len(r), 0))
    refine = [p_lin]
    # Second start: the configuration, unless the data's machine is far from it (then a
    # start there costs evaluations and finds nothing the data's start does not).
    if not configuration_notes(p_lin, p0):
        alt = p0 if p0 != p_lin else p0.replace(J_S=p0.J_S * 2.0, K_coulomb=p0.K_coulomb * 0.5)
        refine.append(alt.replace(K_stiction=max(alt.K_stiction, alt.K_coulomb)))
    # Third start: the linear start with its breakaway scanned first.  A stiction far from
    # the configured one made the first fit move Coulomb friction and K_v to absorb it (a
    # local minimum the later scan could not leave: K_coulomb 0.026 for 0.015).
    p_st, _ = scan_stiction(p_lin, Effects(), grid, fit_data, w)
    if p_st.K_stiction != p_lin.K_stiction:
        refine.append(p_st)

    def refined(p_start: VehicleParams, say: Progress) -> FitResult:
        return fit_with_stiction(p_start, Effects(), free, fit_data, w, grid, say, max_nfev=80)

    fits = [*fan_out(mapper, refined, refine, progress), *starts]
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
    return min(near, key=lambda m: val_cost(m, val_data, w))


NEAR_SSE = 0.5
"""Seed fits within this fraction of the best estimation cost go to the validation data."""


DETERMINED = 0.1
"""A constant of the linear estimate is called determined when its relative standard
error is below this."""


REF_FLOOR = 1e-3
"""A free parameter nearer 0 than this fraction of its scale (a Coulomb friction fitted
to its zero bound) is perturbed by this fraction of its scale, not of its value: a step
relative to 6e-14 moved nothing, and the trade-off it hides (kS against kA on slow
symmetric ramps) vanished from the information."""

COND_FLOOR = 1e-12
"""Eigenvalues of the information below this fraction of its largest count as this
(a direction the data do not see has a huge variance, not none)."""


def fisher_rel_se(
    m: FitResult, free: Sequence[Param], data: list[Series], w: Weights
) -> tuple[float, float, float] | None:
    """Relative standard errors of (kS, kV, kA) of the simulation-error fit ``m`` on
    ``data``, from the Fisher information (Gauss-Newton, finite differences in log
    space; :data:`REF_FLOOR` for a parameter at 0), the residual's variance, and its
    lag-1 autocorrelation to count effectively independent samples (an autocorrelated
    residual carries less information).  A direction the data do not see
    (:data:`COND_FLOOR`) has a huge variance.  None when the seed's ``K_v``, ``J_S`` or
    ``K_coulomb`` is not free."""
    names = [f.name for f in free]
    if not {"K_v", "J_S", "K_coulomb"} <= set(names):
        return None
    r0 = residuals(m.params, m.effects, data, w)
    cols = []
    to_log = []  # per parameter: its reference over its value (to relative units)
    step = 1e-3
    th = theta_of(m.params, m.effects, free)
    for k, f in enumerate(free):
        val = value_of(m.params, m.effects, f.name)
        ref = max(abs(val), REF_FLOOR * abs(f.scale))
        th_up = th.copy()
        th_up[k] = (val + step * ref) / f.scale
        p_up, e_up = apply(m.params, m.effects, free, th_up)
        r_up = residuals(p_up, e_up, data, w)
        cols.append((r_up - r0) / step)  # per unit relative change of the reference
        to_log.append(ref / abs(val) if val != 0.0 else float("inf"))
    jac = np.column_stack(cols)
    n = len(r0)
    if n <= len(free):
        return None
    res = r0 - np.mean(r0)
    rho = float(res[:-1] @ res[1:]) / max(float(res @ res), 1e-300)
    rho = min(max(rho, 0.0), 0.99)
    var = float(r0 @ r0) / (n - len(free)) * (1.0 + rho) / (1.0 - rho)
    info = jac.T @ jac
    if not np.all(np.isfinite(info)):
        return None
    lam, vec = np.linalg.eigh(info)
    lam = np.maximum(lam, COND_FLOOR * max(float(lam[-1]), 1e-300))
    cov_ref = var * (vec / lam) @ vec.T
    with np.errstate(invalid="ignore", over="ignore"):
        scale = np.asarray(to_log)
        cov = cov_ref * np.outer(scale, scale)  # in log units of the values
    kv, js, kc = names.index("K_v"), names.index("J_S"), names.index("K_coulomb")
    d = np.sqrt(np.maximum(np.diag(cov), 0.0))
    # kA = R_m J_S / (K_T ratio) with K_T tied to K_v: log kA = log J_S - log K_v + c.
    ka = float(np.sqrt(max(cov[js, js] + cov[kv, kv] - 2.0 * cov[js, kv], 0.0)))
    ks = float(np.sqrt(max(cov[kc, kc] + cov[kv, kv] - 2.0 * cov[kc, kv], 0.0)))
    if not m.params.K_coulomb > REF_FLOOR * abs(free[kc].scale):
        ks = float("inf")  # at its zero bound: no relative error to speak of
    return ks, float(d[kv]), ka


@dataclass(frozen=True)
class Seed:
    """What the seed stage hands on."""

    fit: FitResult
    """The seed model (no effects) fitted on the estimation data."""
    model: Model
    """``fit`` with its validation cost: the model every candidate is tried against."""
    free: list[Param]
    """The seed's free parameters (every later fit frees them too)."""
    grid: tuple[float, ...]
    """The stiction values scanned after each fit."""
    fisher: tuple[float, float, float] | None
    """Relative standard errors of kS, kV, kA of ``fit`` (:func:`fisher_rel_se`)."""


def seed_stage(
    prep: Prepared, start: LinearStart, progress: Progress, mapper: Mapper = in_order
) -> Seed:
    """Stage 3 of the diagnosis: the seed (motor, inertia, Coulomb, stiction) fitted by
    simulation error from the least-squares stage's starts (through ``mapper``)."""
    free = seed_params(start.p_lin, prep.whole.i is not None)
    grid = stiction_grid(prep.p0, prep.whole)
    fit = fit_seed(
        prep.p0, start.p_lin, free, prep.fit_data, prep.w, grid, progress, start.ls,
        prep.val_data, mapper,
    )  # fmt: skip
    return Seed(
        fit=fit,
        model=Model(fit, (), val_cost(fit, prep.val_data, prep.w)),
        free=free,
        grid=grid,
        fisher=fisher_rel_se(fit, free, prep.fit_data, prep.w),
    )
