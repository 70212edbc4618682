"""A model extended by one candidate effect: grid start, then joint refit.

Used by the candidate stage (each candidate alone on the seed) and the selection
stage (a candidate on top of those accepted, a pair, a swap) of
:mod:`truckd.ident.diagnose`.  Pure numerics.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from truckd.ident.candidates import (
    Candidate,
)
from truckd.ident.data import (
    Series,
)
from truckd.ident.scoring import Progress, val_cost
from truckd.ident.voltage import (
    FitResult,
    Param,
    Weights,
    fit,
    fit_with_stiction,
    residuals,
    scan,
    value_cost,
)
from truckd.model.effects import Effects


def fit_candidate(
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
        if cand.every_start and not base.effects.active():
            # The seed's constants absorbed the limit: the value best on them may start
            # in the wrong basin (a current limit of 22 A fitted 64 A, with K_v 4x off).
            # A few steps from each tighter start probe its basin (breakaway at Coulomb:
            # at a tight limit the seed's stiction can hold the truck still, and the fit
            # sees no slope); the best probe, when it already fits better, is refitted in
            # full, stiction scanned.
            p_probe = base.params.replace(K_stiction=base.params.K_coulomb)
            probes = [
                fit(
                    p_probe, dataclasses.replace(e_base, **{name: g}), [*free, *own],
                    fit_data, w, max_nfev=PROBE_NFEV,
                )
                for g in tighter_starts(cand.grid, value)
            ]  # fmt: skip
            pb = min(probes, key=lambda m: m.sse, default=None)
            if pb is not None and pb.sse < out.sse:
                full = fit_with_stiction(
                    pb.params, pb.effects, [*free, *own], fit_data, w, grid, progress
                )
                out = full if full.sse < out.sse else out
        if cand.param.name == "hill_force":
            out = refine_stretch(out, [*free, cand.param], fit_data, w, grid, progress)
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
        tau = p.mechanical_time_constant
        j_lo = min(f.lo for f in seed_free if f.name == "J_S")
        alt = p.replace(J_S=max(0.05 * p.J_S, 1.01 * j_lo))
        e_alt = dataclasses.replace(base.effects, sensor_lag=0.95 * tau)
        second = fit_with_stiction(alt, e_alt, [*free, cand.param], fit_data, w, grid, progress)
        out = second if second.sse < out.sse else out
    # Never worse than without the candidate (a local minimum): then it is simply off.
    return out if out.sse <= base.sse else base


TIGHTER_STARTS = 3
"""Starts of a limit's joint fit below the value best on the seed's constants."""
PROBE_NFEV = 6
"""Evaluations of the probe fit from each such start."""


def tighter_starts(grid: Sequence[float], best: float) -> list[float]:
    """Up to :data:`TIGHTER_STARTS` grid values below ``best``, spread over them: a seed
    that absorbed a limit fits best with the limit loose (its constants are the ones
    of a slow, weak truck), so the right basin lies at a tighter limit."""
    below = sorted(g for g in grid if g < best)
    if len(below) <= TIGHTER_STARTS:
        return below
    picks = np.linspace(0, len(below) - 1, TIGHTER_STARTS).round().astype(int)
    return [below[int(k)] for k in picks]


def params_of(cand: Candidate, e: Effects) -> dict[str, float]:
    """The candidate's fitted parameter and its held ones (a hill's start, length)."""
    out = {cand.param.name: float(getattr(e, cand.param.name))}
    for n, _ in cand.preset:
        out[n] = float(getattr(e, n))
    return out


def profile_of(cand: Candidate, e: Effects) -> dict[str, float | str] | None:
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


def refine_stretch(
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
    cost = value_cost(m.params, m.effects, name, fit_data, w)
    costs = {float(val): cost(float(val)) for val in values}
    low = min(costs.values())
    ties = [v for v, c in costs.items() if c <= low * (1.0 + 1e-9) + 1e-12]
    if len(ties) < 2:
        return m
    best = min(
        ties,
        key=lambda v: val_cost(
            dataclasses.replace(m, effects=dataclasses.replace(m.effects, **{name: v})),
            val_data,
            w,
        ),
    )
    eff = dataclasses.replace(m.effects, **{name: best})
    return dataclasses.replace(m, effects=eff, sse=costs[best])
