"""Locating a position-dependent load (a hill, a bump) from a log's residual.

The seed model's equation error, as a force at the wheels (N), is binned by position
(m).  A load that lives on a stretch of road shows as a run of bins whose median lies
away from the rest; the stretch with the largest summed deviation is the hill's first
guess.  The simulation-error fit then refines its force, start and length
(:mod:`truckd.ident.diagnose`).  Rolling terrain is the sinusoid in position that best
fits the same binned residual (:func:`locate_wave`).  Pure numerics.

How it is told apart from time- or speed-dependent effects: the residual of an input
delay, a sensor lag or aero drag follows the command or the speed, so binned by
position it spreads over every place the truck drove at that speed; a hill's residual
sits in one stretch of road.  A truck that crossed the stretch once at one speed leaves
the two explanations close; the selection then reports them ``ambiguous``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident.data import Series
from truckd.model.params import VehicleParams

MIN_SAMPLES_TRAVEL = 3
"""A stretch shorter than this many samples of travel at the median speed is not seen."""
BINS = 120
"""Position bins over the driven range (at most)."""
MAX_FRACTION = 0.6
"""A stretch covering more than this fraction of the driven range is no hill (it is a
constant load, which the ``load_force`` candidate covers)."""
GRADE_MAX = 0.35
"""Steepest plausible grade (35 %, about 19 degrees): ``|hill_force| <= GRADE_MAX m g``
(the grade force is ``m g sin(atan(grade))``, below ``GRADE_MAX m g``)."""


@dataclass(frozen=True)
class Stretch:
    """A located stretch of road (m) and the mean extra force on it (N, + opposes)."""

    start: float
    length: float
    force: float
    bin_width: float


def _smooth(y: np.ndarray, k: int) -> np.ndarray:
    if k <= 1 or len(y) < 2 * k:
        return y
    ker = np.ones(k) / k
    return np.convolve(np.pad(y, (k // 2, k - 1 - k // 2), mode="edge"), ker, mode="valid")


def residual_force(p: VehicleParams, s: Series) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equation error of run ``s`` as a force at the wheels (N).

    The linear model ``u = kS sign(v) + kV v + kA a + c`` (SysId's, with an offset) is
    fitted to the run itself (so a seed model that absorbed part of the load does not
    hide it) and its voltage residual converted to force with ``p``'s motor constants.
    Returns ``(position m, force N, usable mask)``; samples at rest or near a speed
    reversal are not usable (stiction decides there, not the load).
    """
    if s.x is None:
        raise ValueError("a run needs a position (truckd.ident.data.with_position)")
    h = float(np.median(np.diff(s.t)))
    k = max(3, round(0.05 / h))
    v = _smooth(s.v, k)
    a = np.gradient(v, s.t)
    v_scale = max(float(np.max(np.abs(v))), 1e-9)
    usable = np.abs(v) > 0.1 * v_scale
    x_mat = np.column_stack([np.sign(v), v, a, np.ones_like(v)])
    if usable.sum() < 10:
        return s.x, np.zeros_like(v), usable
    coef, *_ = np.linalg.lstsq(x_mat[usable], _smooth(s.inp, k)[usable], rcond=None)
    volts = _smooth(s.inp, k) - x_mat @ coef
    force = volts * p.K_T / (p.R_m * p.ratio)
    return s.x, force, usable


@dataclass(frozen=True)
class Profile:
    """The residual force binned by position: bin starts (m), deviation from the
    median (N), which bins hold data, bin width (m), driven range (m)."""

    left: np.ndarray
    dev: np.ndarray
    have: np.ndarray
    width: float
    span: float
    min_len: float


def profile(p: VehicleParams, runs: Sequence[Series]) -> Profile | None:
    """Residual force binned by position over all runs (None: too little travel)."""
    xs, fs = [], []
    travel = []
    for r in runs:
        x, f, ok = residual_force(p, r)
        xs.append(x[ok])
        fs.append(f[ok])
        h = float(np.median(np.diff(r.t)))
        travel.append(float(np.median(np.abs(r.v))) * h)
    x = np.concatenate(xs)
    f = np.concatenate(fs)
    if len(x) < 50:
        return None
    lo, hi = float(np.min(x)), float(np.max(x))
    span = hi - lo
    min_len = MIN_SAMPLES_TRAVEL * max(travel)
    if span <= 3.0 * min_len:
        return None
    width = max(span / BINS, min_len / 2.0)
    nb = max(int(np.ceil(span / width)), 1)
    idx = np.minimum(((x - lo) / width).astype(int), nb - 1)
    med = np.full(nb, np.nan)
    for b in range(nb):
        sel = f[idx == b]
        if len(sel) >= 3:
            med[b] = float(np.median(sel))
    have = np.isfinite(med)
    if have.sum() < 10:
        return None
    dev = np.where(have, med - float(np.median(med[have])), 0.0)
    left = lo + width * np.arange(nb)
    return Profile(left, dev, have, width, span, min_len)


def locate(p: VehicleParams, runs: Sequence[Series]) -> Stretch | None:
    """The stretch of road where the residual force is localised, or None."""
    prof = profile(p, runs)
    if prof is None:
        return None
    dev, have, width, span = prof.dev, prof.have, prof.width, prof.span
    nb = len(dev)
    best = (0.0, 0, 0)
    for sign in (1.0, -1.0):
        run_sum, start = 0.0, 0
        for b in range(nb):
            if run_sum <= 0.0:
                run_sum, start = 0.0, b
            run_sum += sign * dev[b]
            if run_sum > best[0]:
                best = (run_sum, start, b + 1)
    total, b0, b1 = best
    if total <= 0.0 or (b1 - b0) * width > MAX_FRACTION * span:
        return None
    # Trim to the plateau: the bins carrying at least half the stretch's mean deviation.
    sign = 1.0 if float(np.sum(dev[b0:b1])) > 0.0 else -1.0
    mean = sign * float(np.mean(dev[b0:b1][have[b0:b1]]))
    strong = np.flatnonzero(sign * dev[b0:b1] >= 0.5 * mean)
    if strong.size:
        b0, b1 = b0 + int(strong[0]), b0 + int(strong[-1]) + 1
    force = float(np.mean(dev[b0:b1][have[b0:b1]]))
    return Stretch(
        start=float(prof.left[b0]), length=(b1 - b0) * width, force=force, bin_width=width
    )


@dataclass(frozen=True)
class Wave:
    """Rolling terrain: ``amplitude sin(2 pi x / wavelength + phase)`` (N, m, rad)."""

    amplitude: float
    wavelength: float
    phase: float


def locate_wave(p: VehicleParams, runs: Sequence[Series]) -> Wave | None:
    """The sinusoid in position that best explains the binned residual force, or None.

    Wavelengths from 4 bins (and 2 x the shortest visible stretch) to half the driven
    range, on a log grid; sine and cosine fitted by least squares at each.
    """
    prof = profile(p, runs)
    if prof is None:
        return None
    lo_w = max(4.0 * prof.width, 2.0 * prof.min_len)
    hi_w = 0.5 * prof.span
    if hi_w <= lo_w:
        return None
    xc = (prof.left + 0.5 * prof.width)[prof.have]
    y = prof.dev[prof.have]
    best: tuple[float, Wave] | None = None
    for lam in np.geomspace(lo_w, hi_w, 80):
        k = 2.0 * np.pi / lam
        a_mat = np.column_stack([np.sin(k * xc), np.cos(k * xc), np.ones_like(xc)])
        coef, *_ = np.linalg.lstsq(a_mat, y, rcond=None)
        sse = float(np.sum((y - a_mat @ coef) ** 2))
        amp = float(np.hypot(coef[0], coef[1]))
        wave = Wave(amp, float(lam), float(np.arctan2(coef[1], coef[0])))
        if best is None or sse < best[0]:
            best = (sse, wave)
    return None if best is None else best[1]


def rolling_problem(
    amplitude: float, wavelength: float, p: VehicleParams, runs: Sequence[Series]
) -> str | None:
    """Why rolling terrain of ``amplitude`` N and ``wavelength`` m is impossible."""
    weight = p.m * 9.81
    if abs(amplitude) > GRADE_MAX * weight:
        return (
            f"load_force_amplitude = {abs(amplitude):.3g} N exceeds a {GRADE_MAX:.0%} grade "
            f"of the truck's weight ({GRADE_MAX * weight:.3g} N)"
        )
    travel = max(float(np.median(np.abs(r.v))) * float(np.median(np.diff(r.t))) for r in runs)
    if wavelength < 2.0 * MIN_SAMPLES_TRAVEL * travel:
        return (
            f"load_force_wavelength = {wavelength:.3g} m shorter than "
            f"{2 * MIN_SAMPLES_TRAVEL} samples of travel"
        )
    return None


def hill_problem(
    force: float, start: float, length: float, p: VehicleParams, runs: Sequence[Series]
) -> str | None:
    """Why a hill of ``force`` N on ``[start, start + length)`` m is impossible (None: fine)."""
    weight = p.m * 9.81
    if abs(force) > GRADE_MAX * weight:
        return (
            f"|hill_force| = {abs(force):.3g} N exceeds a {GRADE_MAX:.0%} grade of the truck's "
            f"weight ({GRADE_MAX * weight:.3g} N)"
        )
    xs = [r.x for r in runs if r.x is not None]
    if xs:
        lo = min(float(np.min(x)) for x in xs)
        hi = max(float(np.max(x)) for x in xs)
        if start < lo or start + length > hi:
            return (
                f"hill [{start:.3g}, {start + length:.3g}] m outside the driven range "
                f"[{lo:.3g}, {hi:.3g}] m"
            )
    travel = max(float(np.median(np.abs(r.v))) * float(np.median(np.diff(r.t))) for r in runs)
    if length < MIN_SAMPLES_TRAVEL * travel:
        return f"hill_length = {length:.3g} m shorter than {MIN_SAMPLES_TRAVEL} samples of travel"
    return None
