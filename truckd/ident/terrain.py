"""Locating a position-dependent load (a hill, a bump) from a log's residual.

A hill is found by a linear output-error scan: with the seed model's mechanical time
constant ``tau = kA/kV`` held, the simulated speed of every stretch of motion (started
from its measured speed) is linear in the command gain, the Coulomb and constant loads
and a force on any stretch of road ``[a, b)``, because the indicator of the stretch is
known along the measured trajectory.  Each of these inputs is passed through the same
first-order filter; the indicator of a stretch is a sum of per-bin filtered indicators,
so every start and end on a grid of position bins is scored at once (the sum of squares
it removes, by partial regression on the other inputs).  The stretch is chosen with a
constant load allowed (where the level steps), then oriented without it (a load on the
stretch, or on the rest of the road, whichever is a hill).  The simulation-error fit
then refines its force, start and length (:func:`truckd.ident.extend.refine_stretch`).

Why output error and not the equation error (force = u - kS sign v - kV v - kA a): the
equation error differentiates the measured speed, whose noise then grows as ``kA`` over
the sample time; on a heavy, weak truck (long ``tau``) a hill's force is far below that
noise, while the speed it costs lasts ``tau`` and is seen by every sample meanwhile.

Rolling terrain is the sinusoid in position that best fits the equation error binned by
position (:func:`locate_wave`).  Pure numerics.

How a hill is told apart from time- or speed-dependent effects: the residual of an input
delay, a sensor lag or aero drag follows the command or the speed, so binned by position
it spreads over every place the truck drove at that speed; a hill's residual sits in one
stretch of road.  A stretch the truck never leaves is a constant load (``load_force``):
the scan needs data on and off the stretch.  A truck that crossed the stretch once at
one speed leaves the explanations close; the selection then reports them ``ambiguous``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from truckd.ident import ckernel
from truckd.ident.data import Series
from truckd.ident.linear import feedforward_of
from truckd.model.params import VehicleParams

MIN_SAMPLES_TRAVEL = 3
"""A stretch shorter than this many samples of travel at the median speed is not seen."""
BINS = 120
"""Position bins over the driven range (at most)."""
MIN_SHARE = 0.03
"""A stretch is scored only with at least this share of the moving samples (and
:data:`MIN_ROWS`) both on it and off it: one the truck never leaves is a constant load,
one it hardly visits is not seen."""
MIN_ROWS = 50
GRID_MAX = 20000
"""Most points of the uniform time grid the scan filters on (over all runs)."""
ROWS_MAX = 8000
"""Most grid points used as rows of the scan's regression."""
MOVING = 0.1
"""Samples slower than this fraction of the top speed are left out (stiction decides
there, and near a reversal the Coulomb force flips)."""
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
    force = volts * newtons_per_volt(p)
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


@dataclass(frozen=True)
class _Rows:
    """The scan's regression: target (m/s), base inputs (u, sign v, 1) and per-bin
    indicators, all filtered; moving samples per bin; the position grid."""

    y: np.ndarray
    base: np.ndarray
    bins: np.ndarray
    count: np.ndarray
    lo: float
    hi: float
    width: float
    min_len: float


def _grid(s: Series, hg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run ``s`` on a uniform time grid of step ``hg``: the command averaged over each
    step (it is held between samples), speed and position at the grid points, and the
    position at the middle of each step."""
    assert s.x is not None
    t = s.t
    m = max(int((t[-1] - t[0]) / hg), 1)
    edges = t[0] + hg * np.arange(m + 1)
    held = np.concatenate([[0.0], np.cumsum(s.inp[:-1] * np.diff(t))])

    def integral(tq: np.ndarray) -> np.ndarray:
        j = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 1)
        return np.asarray(held[j] + s.inp[j] * (tq - t[j]))

    u = np.diff(integral(edges)) / hg
    tg = edges[:-1]
    return u, np.interp(tg, t, s.v), np.interp(tg, t, s.x), np.interp(tg + 0.5 * hg, t, s.x)


def time_constant(p: VehicleParams) -> float | None:
    """The model's mechanical time constant ``kA/kV`` (s), None if not positive."""
    ff = feedforward_of(p)
    if not (ff.kV > 0.0 and ff.kA > 0.0):
        return None
    return ff.kA / ff.kV


def newtons_per_volt(p: VehicleParams) -> float:
    """Force at the wheels (N) per volt of command at stall: ``K_T / (R_m ratio)``."""
    return p.K_T / (p.R_m * p.ratio)


def _step(runs: Sequence[Series], r: Series) -> float:
    """Grid step of run ``r``: its sample time, coarser for long logs (:data:`GRID_MAX`)."""
    duration = sum(float(q.t[-1] - q.t[0]) for q in runs)
    return max(float(np.median(np.diff(r.t))), duration / GRID_MAX)


def _filtered(
    r: Series, hg: float, tau: float, where: Callable[[np.ndarray, np.ndarray], np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run ``r`` on the grid, each stretch of motion simulated from its measured speed by
    the first-order filter of time constant ``tau``: ``(target speed, filtered inputs,
    moving, position mid-step, direction)``.  The inputs are the command, ``sign v``, 1 and the
    columns ``where(position mid-step, sign v)`` (indicators of places of the road)."""
    u, v, _, x_mid = _grid(r, hg)
    vs = _smooth(v, max(3, round(0.05 / hg)))
    moving = np.abs(vs) > MOVING * max(float(np.max(np.abs(vs))), 1e-9)
    sign = np.sign(vs)
    inputs = np.column_stack([u, sign, np.ones_like(u), where(x_mid, sign)])
    a = float(np.exp(-hg / tau))
    filt = ckernel.first_order(inputs, 1.0 - a, -a)
    if filt is None:  # the C kernel is not built: scipy's filter, the same numbers
        from scipy.signal import lfilter  # here: scipy.signal takes a second to import

        filt = np.asarray(lfilter([0.0, 1.0 - a], [1.0, -a], inputs, axis=0))
    target = v.copy()
    new = np.flatnonzero(
        np.concatenate([[True], (moving[1:] != moving[:-1]) | (sign[1:] != sign[:-1])])
    )
    for i0, i1 in zip(new, [*new[1:], len(u)], strict=True):
        if not moving[i0]:
            continue
        decay = a ** np.arange(i1 - i0)
        filt[i0:i1] -= decay[:, None] * filt[i0][None, :]
        target[i0:i1] -= decay * vs[i0]
    return target, filt, moving, x_mid, sign


def _rows(p: VehicleParams, runs: Sequence[Series]) -> _Rows | None:
    """The filtered inputs of every stretch of motion, each started from its measured
    speed (None: no usable time constant, too little motion or travel)."""
    tau = time_constant(p)
    if tau is None:
        return None
    xs = [r.x for r in runs if r.x is not None]
    if len(xs) != len(runs):
        raise ValueError("a run needs a position (truckd.ident.data.with_position)")
    lo = min(float(np.min(x)) for x in xs)
    hi = max(float(np.max(x)) for x in xs)
    span = hi - lo
    travel = max(float(np.median(np.abs(r.v))) * float(np.median(np.diff(r.t))) for r in runs)
    min_len = MIN_SAMPLES_TRAVEL * travel
    if span <= 3.0 * min_len:
        return None
    width = max(span / BINS, min_len / 2.0)
    nb = max(int(np.ceil(span / width)), 1)
    stride = max(1, min(sum(len(r) for r in runs), GRID_MAX) // ROWS_MAX)

    def bin_of(x: np.ndarray) -> np.ndarray:
        return np.asarray(np.minimum(np.maximum(((x - lo) / width).astype(int), 0), nb - 1))

    def onehot(x: np.ndarray, _: np.ndarray) -> np.ndarray:
        out = np.zeros((len(x), nb))
        out[np.arange(len(x)), bin_of(x)] = 1.0
        return out

    ys, bases, binss = [], [], []
    count = np.zeros(nb)
    for r in runs:
        if len(r) < 10:
            continue
        target, filt, moving, x_mid, _ = _filtered(r, _step(runs, r), tau, onehot)
        use = np.flatnonzero(moving)[::stride]
        ys.append(target[use])
        bases.append(filt[use, :3])
        binss.append(filt[use, 3:])
        count += np.bincount(bin_of(x_mid[use]), minlength=nb)
    if not ys or sum(len(y) for y in ys) < 4 * MIN_ROWS:
        return None
    return _Rows(
        y=np.concatenate(ys),
        base=np.concatenate(bases),
        bins=np.concatenate(binss),
        count=count,
        lo=lo,
        hi=hi,
        width=width,
        min_len=min_len,
    )


def direction_forces(
    p: VehicleParams, runs: Sequence[Series], start: float, end: float
) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The load (N) on ``[start, end)`` fitted separately for forward and backward
    travel, each with its standard error: ``((f_fwd, se), (f_bwd, se))`` (se infinite
    for a direction with too little data; None: no usable time constant).

    A hill pushes the same way whichever way the truck drives over it; a misfit of a
    speed-dependent term (back-EMF, drag, friction) pushes against the motion, so it
    changes sign with the direction."""
    tau = time_constant(p)
    if tau is None:
        return None

    def split(x: np.ndarray, sign: np.ndarray) -> np.ndarray:
        on = (x >= start) & (x < end)
        return np.column_stack([on & (sign > 0), on & (sign < 0)]).astype(float)

    ys, cols, counts = [], [], []
    for r in runs:
        if len(r) < 10:
            continue
        target, filt, moving, x_mid, sign = _filtered(r, _step(runs, r), tau, split)
        ys.append(target[moving])
        cols.append(filt[moving][:, [0, 1, 3, 4]])
        counts.append(split(x_mid, sign)[moving].sum(axis=0))
    if not ys:
        return None
    y = np.concatenate(ys)
    x_mat = np.concatenate(cols)
    have = np.sum(counts, axis=0) >= MIN_ROWS
    gram = x_mat.T @ x_mat
    keep = [0, 1, *(2 + k for k in range(2) if have[k])]
    sub = gram[np.ix_(keep, keep)]
    if len(y) <= len(keep) or np.linalg.cond(sub) > 1e12:
        return None
    coef = np.linalg.solve(sub, x_mat[:, keep].T @ y)
    resid = y - x_mat[:, keep] @ coef
    var = float(resid @ resid) / (len(y) - len(keep)) * np.diag(np.linalg.inv(sub))
    if not coef[0] > 0.0:
        return None
    per_unit = newtons_per_volt(p)
    out: list[tuple[float, float]] = []
    for k in range(2):
        if not have[k]:
            out.append((0.0, float("inf")))
            continue
        j = keep.index(2 + k)
        out.append((-coef[j] / coef[0] * per_unit, float(np.sqrt(var[j])) / coef[0] * per_unit))
    return out[0], out[1]


def _scan(
    rows: _Rows, base: np.ndarray, force_max: float, per_unit: float
) -> tuple[np.ndarray, np.ndarray]:
    """Every stretch of bins ``[i, j)``: the sum of squares a load on it removes from the
    regression on ``base`` and that load (N; -inf and 0 where not allowed)."""
    gram = base.T @ base
    if np.linalg.cond(gram) > 1e12:
        nb = rows.bins.shape[1] + 1
        return np.full((nb, nb), -np.inf), np.zeros((nb, nb))
    inv = np.linalg.inv(gram)
    coef = inv @ (base.T @ rows.y)
    resid = rows.y - base @ coef
    nb = rows.bins.shape[1]
    cum_g = np.concatenate([[0.0], np.cumsum(rows.bins.T @ resid)])
    cum_p = np.hstack([np.zeros((base.shape[1], 1)), np.cumsum(base.T @ rows.bins, axis=1)])
    cum_m = np.zeros((nb + 1, nb + 1))
    cum_m[1:, 1:] = np.cumsum(np.cumsum(rows.bins.T @ rows.bins, axis=0), axis=1)
    cum_n = np.concatenate([[0.0], np.cumsum(rows.count)])
    g = cum_g[None, :] - cum_g[:, None]
    q = cum_p[:, None, :] - cum_p[:, :, None]
    diag = np.diag(cum_m)
    own = diag[None, :] - cum_m - cum_m.T + diag[:, None]
    denom = own - np.einsum("kij,kl,lij->ij", q, inv, q)
    on = cum_n[None, :] - cum_n[:, None]
    n_min = max(float(MIN_ROWS), MIN_SHARE * float(cum_n[-1]))
    i, j = np.indices(g.shape)
    ok = (j > i) & (denom > 1e-9 * max(float(np.max(own)), 1e-300))
    ok &= (on >= n_min) & (cum_n[-1] - on >= n_min) & ((j - i) * rows.width >= rows.min_len)
    gain = coef[0]
    if not gain > 0.0:
        return np.full(g.shape, -np.inf), np.zeros(g.shape)
    load = np.where(ok, g / np.where(ok, denom, 1.0), 0.0)
    force = -load / gain * per_unit
    ok &= np.abs(force) <= force_max
    return np.where(ok, g**2 / np.where(ok, denom, 1.0), -np.inf), np.where(ok, force, 0.0)


def locate(p: VehicleParams, runs: Sequence[Series]) -> Stretch | None:
    """The stretch of road where a load best explains the runs' speed, or None.

    See the module docstring: scanned with a constant load allowed, oriented without.
    """
    rows = _rows(p, runs)
    if rows is None:
        return None
    per_unit = newtons_per_volt(p)
    force_max = GRADE_MAX * p.m * 9.81
    with_load, _ = _scan(rows, rows.base, force_max, per_unit)
    if not np.isfinite(np.max(with_load)):
        return None
    i, j = (int(k) for k in np.unravel_index(int(np.argmax(with_load)), with_load.shape))
    nb = with_load.shape[0] - 1
    options = [(i, j)]
    if i == 0 and j < nb:
        options.append((j, nb))
    if j == nb and i > 0:
        options.append((0, i))
    alone, force = _scan(rows, rows.base[:, :2], force_max, per_unit)
    i, j = max(options, key=lambda o: float(alone[o]))
    if not np.isfinite(alone[i, j]):
        return None
    start = rows.lo + i * rows.width
    end = min(rows.lo + j * rows.width, rows.hi)
    if not both_ways_agree(p, runs, start, end):
        return None
    return Stretch(start=start, length=end - start, force=float(force[i, j]), bin_width=rows.width)


AGREE = 0.5
"""A load seen both ways is a hill when the two directions' forces have one sign and
differ by at most this fraction of the larger (plus twice their standard error)."""


def both_ways_agree(p: VehicleParams, runs: Sequence[Series], start: float, end: float) -> bool:
    """Whether the load on ``[start, end)`` is the same for both directions of travel
    (True too when the runs cross it in one direction only: nothing to compare)."""
    dirs = direction_forces(p, runs, start, end)
    if dirs is None:
        return True
    (f_fwd, se_fwd), (f_bwd, se_bwd) = dirs
    if not (np.isfinite(se_fwd) and np.isfinite(se_bwd)):
        return True
    spread = AGREE * max(abs(f_fwd), abs(f_bwd)) + 2.0 * float(np.hypot(se_fwd, se_bwd))
    return f_fwd * f_bwd > 0.0 and abs(f_fwd - f_bwd) <= spread


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


def over_weight(label: str, force: float, mass: float) -> str | None:
    """Why a load of ``force`` N (``label`` names it) is impossible on a machine of
    ``mass`` kg (the fitted one, :func:`truckd.ident.physics.fitted_mass`): above the
    weight it implies (None: fine).  One rule for a constant load, a hill, rolling terrain."""
    weight = mass * 9.81
    if abs(force) > weight:
        return (
            f"{label} = {abs(force):.3g} N exceeds the weight the fitted inertia implies "
            f"({weight:.3g} N)"
        )
    return None


def rolling_problem(
    amplitude: float,
    wavelength: float,
    p: VehicleParams,
    runs: Sequence[Series],
    mass: float | None = None,
) -> str | None:
    """Why rolling terrain of ``amplitude`` N and ``wavelength`` m is impossible;
    ``mass`` (kg) the fitted machine's (:func:`truckd.ident.physics.fitted_mass`): no
    load exceeds the weight it implies, as a constant load may not (a flywheel with its
    wheels off the ground weighs on nothing)."""
    weight = p.m * 9.81
    if abs(amplitude) > GRADE_MAX * weight:
        return (
            f"load_force_amplitude = {abs(amplitude):.3g} N exceeds a {GRADE_MAX:.0%} grade "
            f"of the truck's weight ({GRADE_MAX * weight:.3g} N)"
        )
    if mass is not None and (why := over_weight("load_force_amplitude", amplitude, mass)):
        return why
    travel = max(float(np.median(np.abs(r.v))) * float(np.median(np.diff(r.t))) for r in runs)
    if wavelength < 2.0 * MIN_SAMPLES_TRAVEL * travel:
        return (
            f"load_force_wavelength = {wavelength:.3g} m shorter than "
            f"{2 * MIN_SAMPLES_TRAVEL} samples of travel"
        )
    return None


def hill_problem(
    force: float,
    start: float,
    length: float,
    p: VehicleParams,
    runs: Sequence[Series],
    mass: float | None = None,
) -> str | None:
    """Why a hill of ``force`` N on ``[start, start + length)`` m is impossible (None:
    fine); ``mass`` (kg) as in :func:`rolling_problem`."""
    weight = p.m * 9.81
    if abs(force) > GRADE_MAX * weight:
        return (
            f"|hill_force| = {abs(force):.3g} N exceeds a {GRADE_MAX:.0%} grade of the truck's "
            f"weight ({GRADE_MAX * weight:.3g} N)"
        )
    if mass is not None and (why := over_weight("|hill_force|", force, mass)):
        return why
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
