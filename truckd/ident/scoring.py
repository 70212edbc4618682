"""How the diagnosis scores a model: its validation cost, its free-run figures, the gain
of one model over another where they differ, and the structure left in its residual.
Shared by the stages of :mod:`truckd.ident.diagnose`; pure numerics.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.data import (
    Series,
    fresh_mask,
    merged,
    noise_std,
)
from truckd.ident.linear import (
    feedforward_of,
)
from truckd.ident.residuals import Whiteness, whiteness
from truckd.ident.result import (
    ModelSummary,
)
from truckd.ident.selection import at_noise_level, structured
from truckd.ident.voltage import (
    FitResult,
    Weights,
    fit_percent,
    predict,
    residuals,
    rmse,
)
from truckd.model.effects import COMPANIONS, Effects
from truckd.model.params import VehicleParams

GAIN_MIN = 0.5
"""Points of validation fit a cause must add to be accepted (the selection's test)."""

MIN_SUPPORT = 50
"""Fewest validation samples under a hill's influence to validate it at all."""

SEED_NAMES = ("R_m", "L_m", "K_v", "K_T", "J_S", "K_coulomb", "K_stiction")
"""The seed's parameters, reported with every model."""


@dataclass(frozen=True)
class Model:
    """A fitted model as the selection compares it."""

    fit: FitResult
    names: tuple[str, ...]
    """The candidates it adds to the seed, in order."""
    val_cost: float
    """Its cost on the validation data (:func:`val_cost`)."""


def val_cost(m: FitResult, val: Sequence[Series], w: Weights) -> float:
    """The weighted sum of squared free-run residuals of ``m`` on ``val``."""
    r = residuals(m.params, m.effects, val, w)
    return float(r @ r)


def still_structured(m: FitResult, runs: Sequence[Series]) -> bool:
    """The free-run speed residual of ``m`` on ``runs`` has structure beyond the noise."""
    y, y_sim = free_run(m.params, m.effects, runs)
    return whiteness_of(y - y_sim, runs)[1]


def free_run(p: VehicleParams, e: Effects, runs: Sequence[Series]) -> tuple[np.ndarray, np.ndarray]:
    """Measured and simulated speed of every run (each from its own start), end to end."""
    sims = [predict(p, e, r).v for r in runs]
    return np.concatenate([r.v for r in runs]), np.concatenate(sims)


def gain_where_acting(
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


def _acceleration(r: Series) -> np.ndarray:
    return np.asarray(np.gradient(r.v, r.t), float) if len(r) > 2 else np.zeros(len(r))


RESIDUAL_SIGNALS: dict[str, Callable[[Series], np.ndarray]] = {
    "speed": lambda r: r.v,
    "acceleration": _acceleration,
    "command_sign": lambda r: np.asarray(np.sign(r.inp), float),
    "time": lambda r: np.asarray(r.t - r.t[0], float),
    "position": lambda r: r.x if r.x is not None else np.zeros(len(r)),
}
"""What a residual is compared with (one run's signal, SI units), in the order the notes
list them."""


def residual_signals(runs: Sequence[Series]) -> Iterator[tuple[str, np.ndarray]]:
    """The signals a residual over ``runs`` is compared with (same length, end to end),
    one at a time: on a long log each is as large as the log."""
    for name, signal in RESIDUAL_SIGNALS.items():
        parts = [signal(r) for r in runs]
        yield name, parts[0] if len(parts) == 1 else np.concatenate(parts)


def whiteness_of(r: np.ndarray, runs: Sequence[Series]) -> tuple[Whiteness, bool, bool]:
    """Whiteness statistics of a residual over ``runs``, whether it is structured, and
    whether it is at the noise level (:func:`truckd.ident.selection.at_noise_level`).
    A sampled-and-held speed is judged at its fresh readings only (between them the
    held value is stale by construction, a staircase no model of the truck explains)."""
    whole = merged(runs)
    noise = float(np.mean([noise_std(x.v) for x in runs]))
    fresh = np.concatenate([fresh_mask(x.v) for x in runs])
    r, inp, t = r[fresh], whole.inp[fresh], whole.t[fresh]
    h = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    wt = whiteness(r, inp, noise, max_lag=max(10, round(1.0 / h)))
    floor = 2e-3 * float(np.std(whole.v))
    return wt, structured(wt, noise, floor), at_noise_level(wt, noise, floor)


def summary(
    p: VehicleParams, e: Effects, runs: Sequence[Series]
) -> tuple[ModelSummary, np.ndarray]:
    y, y_sim = free_run(p, e, runs)
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


Progress = Callable[[str], None]
"""Where a stage says what it is doing (one line at a time)."""


def quiet(_: str) -> None:
    """Progress that says nothing."""
    return None
