"""Linear equation-error estimate: the starting point taken from the data, not the config.

WPILib SysId's feedforward model ``V = kS sign(v) + kV v + kA a`` (V, m/s, m/s^2) is the
seed's first-order model in volts (current quasi-static, no viscous friction):

    kV = K_v / ratio,   kA = R_m J_S / (K_T ratio),   kS = R_m K_coulomb / K_T

with ``ratio = r_w / (n_g n_fd)``.  It is fitted by ordinary least squares in its exact
discrete form (as SysId does), ``v[k+L] = alpha v[k] + beta u + gamma sign(v[k])``,
over windows of ``L`` samples at the median step with a nearly constant input ``u``,
while sliding (speed clearly off zero, same sign at both ends), so that a fast truck
(``kA/kV`` near the sample time) is not biased by a finite difference.  ``L`` starts at
1 (or the interval between fresh readings of a speed sensor slower than the log) and is
lengthened towards a third of the time constant found (speed noise biases ``alpha``).
One input level per direction (single steps) cannot separate kS from kV: kS is then
left undetermined.  With current ``i`` the electrical balance ``u = R_m i + K_v omega``
gives ``R_m`` and ``K_v`` on their own.  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.ident.data import Series, noise_std
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]

COLLINEAR = 1e-3
"""Smallest singular value (relative, columns normalised) at which kS is still separate
from kV: below it the input is one level per direction (single steps)."""
WINDOW_TAU = 0.3
"""Window length of the regression as a fraction of the estimated time constant kA/kV."""
WINDOW_MAX_S = 0.2
"""... but at most this long (s): the input must stay nearly constant over a window."""
WINDOW_ROUNDS = 3
"""Re-estimates with the window lengthened to the time constant found."""
U_TOL = 0.05
"""Largest change of the input inside a window, as a fraction of the largest input (a
slow ramp passes, a step edge does not)."""
JITTER = 0.1
"""Sample pairs whose step differs from the median by more than this fraction are skipped."""


@dataclass(frozen=True)
class Feedforward:
    """SysId's feedforward constants: ``kS`` (V), ``kV`` (V s/m), ``kA`` (V s^2/m)."""

    kS: float
    kV: float
    kA: float
    rel_se: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Relative standard errors of (kS, kV, kA) from the regression (inf = not determined)."""
    samples: int = 0

    def to_json(self) -> dict[str, float]:
        return {"kS": float(self.kS), "kV": float(self.kV), "kA": float(self.kA)}


def feedforward_of(p: VehicleParams) -> Feedforward:
    """The seed model's parameters in SysId's form (viscous friction excluded)."""
    r = p.ratio
    return Feedforward(
        kS=p.R_m * p.K_coulomb / p.K_T,
        kV=p.K_v / r,
        kA=p.R_m * p.J_S / (p.K_T * r),
    )


def stale_lag(v: Array) -> int:
    """Samples between fresh speed readings: a speed sensor slower than the log repeats
    its value; pairs one update apart carry the dynamics (1 when every sample is new)."""
    if len(v) < 3:
        return 1
    new = np.flatnonzero(np.diff(v) != 0.0)
    if len(new) < 2:
        return 1
    return max(1, round(float(np.median(np.diff(new)))))


def _pairs(r: Series, h: float, lag: int) -> tuple[Array, Array]:
    """Regressors ``[v_k, mean u over the window, sign v_k]`` and targets ``v_(k+lag)``
    over windows of ``lag`` steps at the nominal step, input nearly constant, sliding."""
    n = len(r)
    if n <= lag + 1:
        return np.zeros((0, 3)), np.zeros(0)
    span = r.t[lag:] - r.t[:-lag]
    v0, v1 = r.v[:-lag], r.v[lag:]
    win = np.lib.stride_tricks.sliding_window_view(r.inp, lag)[: n - lag]
    u_mean = win.mean(axis=1)
    u_ptp = np.ptp(win, axis=1)
    thr = max(3.0 * noise_std(r.v), 0.02 * float(np.max(np.abs(r.v))), 1e-9)
    u_tol = U_TOL * max(float(np.max(np.abs(r.inp))), 1e-9)
    ok = (np.abs(span / (lag * h) - 1.0) < JITTER) & (np.abs(v0) > thr) & (np.abs(v1) > thr)
    ok &= (np.sign(v0) == np.sign(v1)) & (u_ptp <= u_tol)
    return np.column_stack([v0[ok], u_mean[ok], np.sign(v0[ok])]), v1[ok]


def fit_feedforward(runs: Sequence[Series]) -> Feedforward | None:
    """OLS of SysId's equation (exact discrete form) on sliding windows of all runs.

    None when too few windows (or the result is not a stable, positive-gain system).
    """
    h = float(np.median(np.concatenate([np.diff(r.t) for r in runs if len(r) > 1])))
    lag0 = max(stale_lag(r.v) for r in runs)
    lag = lag0
    ff: Feedforward | None = None
    for _ in range(WINDOW_ROUNDS):
        ff = _fit_windows(runs, h, lag)
        if ff is None:
            break
        # Speed noise biases alpha (errors in variables) by about (noise/spread)^2; a
        # window of a good part of the time constant makes 1 - alpha large against it.
        tau = ff.kA / ff.kV
        want = int(np.clip(round(WINDOW_TAU * tau / h), lag0, max(lag0, round(WINDOW_MAX_S / h))))
        if want <= lag:
            break
        lag = want
    return ff


def _fit_windows(runs: Sequence[Series], h: float, lag: int) -> Feedforward | None:
    """:func:`fit_feedforward` with windows of ``lag`` samples."""
    parts = [_pairs(r, h, lag) for r in runs]
    x = np.vstack([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    if len(y) < 10:
        return None
    norms = np.maximum(np.linalg.norm(x, axis=0), 1e-300)
    sv = np.linalg.svd(x / norms, compute_uv=False)
    free_ks = bool(sv[-1] > COLLINEAR * sv[0])
    coef = np.zeros(3)
    if free_ks:
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
        # One level per direction (single steps) leaves kS and kV nearly collinear: a
        # fit without a stable, positive gain falls back to kS undetermined.
        # A negative kS (friction pushing) is not physical either: kS is then left
        # undetermined as well (a slow truck far from steady state shows only kA).
        free_ks = bool(0.0 < coef[0] < 1.0 and coef[1] > 0.0 and coef[2] <= 0.0)
    if not free_ks:
        x = np.column_stack([x[:, :2], np.zeros(len(y))])
        coef = np.zeros(3)
        coef[:2], *_ = np.linalg.lstsq(x[:, :2], y, rcond=None)
    alpha, beta = float(coef[0]), float(coef[1])
    if not (0.0 < alpha < 1.0) or beta <= 0.0:
        return None
    tau = lag * h

    def consts(c: Array) -> Array:
        a, b, g = c
        kv = (1.0 - a) / b
        return np.array([-g / b, kv, -tau * kv / np.log(a)])

    ks, kv, ka = (float(k) for k in consts(coef))
    if not free_ks:
        ks = 0.0
    res = y - x @ coef
    cov = ols_covariance(x, float(res @ res))
    if not free_ks:
        cov[2, 2] = np.inf
    # Delta method with the full covariance (the ramp's alpha and beta correlate).
    jac = np.zeros((3, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = 1e-6 * max(abs(coef[j]), 1e-9)
        jac[:, j] = (consts(coef + d) - consts(coef - d)) / (2.0 * d[j])
    with np.errstate(invalid="ignore"):
        se = np.sqrt(np.maximum(np.diag(jac @ np.nan_to_num(cov, posinf=0.0) @ jac.T), 0.0))
    if not free_ks:
        se[0] = np.inf
    vals = (ks, kv, ka)
    rel = tuple(
        float(e / abs(k)) if k != 0 else float("inf") for e, k in zip(se, vals, strict=True)
    )
    return Feedforward(kS=ks, kV=kv, kA=ka, rel_se=(rel[0], rel[1], rel[2]), samples=len(y))


LIMITED = 0.8
"""Samples whose current is above this share of the largest logged are left out of the
electrical balance (:func:`electrical`): a current limit may hold them."""
MIN_BELOW = 20
"""... unless fewer than this many samples remain."""


def electrical(runs: Sequence[Series], p: VehicleParams) -> tuple[float, float] | None:
    """``(R_m, K_v)`` from ``u = R_m i + K_v omega`` by OLS on logged current (None: no
    fit), on the samples below :data:`LIMITED` of the largest current."""
    if any(r.i is None for r in runs):
        return None
    u = np.concatenate([r.inp for r in runs])
    i = np.concatenate([r.i for r in runs if r.i is not None])
    w = np.concatenate([r.v for r in runs]) / p.ratio
    if i.size == 0:
        return None
    # A current limit holds the current while the command asks for more: there ``u`` is
    # not the motor's voltage.  The samples near the largest current are left out (half
    # the samples of a weak truck held at 22 A gave R_m 2x and K_v 2x the true ones).
    below = np.abs(i) < LIMITED * float(np.max(np.abs(i)))
    if int(below.sum()) >= MIN_BELOW:
        u, i, w = u[below], i[below], w[below]
    x = np.column_stack([i, w])
    if np.linalg.matrix_rank(x) < 2:
        return None
    (rm, kv), *_ = np.linalg.lstsq(x, u, rcond=None)
    if rm <= 0.0 or kv <= 0.0:
        return None
    return float(rm), float(kv)


def start_model(
    p0: VehicleParams, runs: Sequence[Series]
) -> tuple[VehicleParams, Feedforward | None]:
    """The configured vehicle with the parameters the data determine linearly replaced.

    ``K_T`` keeps the configured ``K_T/K_v`` ratio; ``R_m`` comes from the current when
    logged, else stays configured; stiction keeps its configured excess over Coulomb
    (the stiction scan locates it later).  Returns the model and the OLS feedforward.
    """
    ff = fit_feedforward(runs)
    p = p0
    el = electrical(runs, p0)
    if el is not None:
        rm, kv = el
        p = p.replace(R_m=rm, K_v=kv, K_T=p0.K_T * kv / p0.K_v)
    if ff is None:
        return p, None
    r = p0.ratio
    if el is None:
        kv = ff.kV * r
        p = p.replace(K_v=kv, K_T=p0.K_T * kv / p0.K_v)
    j = ff.kA * p.K_T * r / p.R_m
    # kS undetermined: keep the configured breakaway voltage (kS of the configuration).
    ks_v = ff.kS if np.isfinite(ff.rel_se[0]) else feedforward_of(p0).kS
    kc = max(ks_v, 0.0) * p.K_T / p.R_m
    ks = kc + max(p0.K_stiction - p0.K_coulomb, 0.0) * (kc / p0.K_coulomb if p0.K_coulomb else 1)
    return p.replace(J_S=j, K_coulomb=kc, K_stiction=ks), ff


@dataclass(frozen=True)
class LeastSquares:
    """The data's own least-squares model (WPILib SysId's), as a vehicle and constants.

    ``params``: the configured vehicle with ``K_v``, ``J_S``, ``K_coulomb`` (and ``R_m``
    with current) replaced so that it simulates exactly ``V = kS sign(v) + kV v + kA a``
    (``K_stiction = K_coulomb``: SysId has no breakaway); only the gearing of the
    configuration converts units (the ratios ``K_T/K_v`` and ``K_T/R_m`` it keeps cancel
    in the speed).  ``ff``: the constants with their standard errors (V, V s/m, V s^2/m).
    """

    params: VehicleParams
    ff: Feedforward

    @property
    def se(self) -> tuple[float, float, float]:
        """Standard errors of (kS, kV, kA) (inf: not determined)."""
        vals = (self.ff.kS, self.ff.kV, self.ff.kA)
        return (
            float(self.ff.rel_se[0] * abs(vals[0])) if np.isfinite(self.ff.rel_se[0]) else np.inf,
            float(self.ff.rel_se[1] * abs(vals[1])),
            float(self.ff.rel_se[2] * abs(vals[2])),
        )


def _finite_difference_ols(runs: Sequence[Series]) -> Feedforward | None:
    """SysId's older form: OLS of ``V = kS sign(v) + kV v + kA a`` with ``a`` the central
    difference of the speed, over all samples clearly in motion (None: too few)."""
    xs, ys = [], []
    for r in runs:
        if len(r) < 5:
            continue
        a = np.gradient(r.v, r.t)
        thr = max(3.0 * noise_std(r.v), 0.02 * float(np.max(np.abs(r.v))), 1e-9)
        ok = np.abs(r.v) > thr
        xs.append(np.column_stack([np.sign(r.v[ok]), r.v[ok], a[ok]]))
        ys.append(r.inp[ok])
    if not xs:
        return None
    x, y = np.vstack(xs), np.concatenate(ys)
    if len(y) < 10 or np.linalg.matrix_rank(x) < 3:
        return None
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    ks, kv, ka = (float(c) for c in coef)
    if kv <= 0.0 or ka <= 0.0:
        return None
    res = y - x @ coef
    cov = ols_covariance(x, float(res @ res))
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    rel = tuple(
        float(e / abs(k)) if k != 0 else float("inf") for e, k in zip(se, coef, strict=True)
    )
    return Feedforward(
        kS=max(ks, 0.0), kV=kv, kA=ka, rel_se=(rel[0], rel[1], rel[2]), samples=len(y)
    )


def ols_covariance(x: Array, sse: float) -> Array:
    """Covariance of ordinary least-squares coefficients: ``sse / (n - p) (X^T X)^+`` for
    the regressors ``x`` (n samples by p columns) and the residual sum of squares ``sse``."""
    cov: Array = sse / max(x.shape[0] - x.shape[1], 1) * np.linalg.pinv(x.T @ x)
    return cov


def least_squares_model(p0: VehicleParams, runs: Sequence[Series]) -> LeastSquares | None:
    """The least-squares model of ``runs`` (:class:`LeastSquares`): SysId's OLS in its
    exact discrete form (:func:`fit_feedforward`), else its finite-difference form;
    with current, ``R_m`` and ``K_v`` from the electrical balance.  None: too few
    samples in motion for either."""
    ff = fit_feedforward(runs) or _finite_difference_ols(runs)
    if ff is None:
        return None
    r = p0.ratio
    p = p0
    el = electrical(runs, p0)
    if el is not None:
        rm, kv = el
        p = p.replace(R_m=rm, K_v=kv, K_T=p0.K_T * kv / p0.K_v)
    else:
        kv = ff.kV * r
        p = p.replace(K_v=kv, K_T=p0.K_T * kv / p0.K_v)
    ks_v = ff.kS if np.isfinite(ff.rel_se[0]) else 0.0
    kc = max(ks_v, 0.0) * p.K_T / p.R_m
    j = ff.kA * p.K_T * r / p.R_m
    return LeastSquares(p.replace(J_S=j, K_coulomb=kc, K_stiction=kc), ff)


@dataclass(frozen=True)
class LinearStart:
    """What the least-squares stage hands on: the starting truck and both estimates."""

    p_lin: VehicleParams
    """The configured truck with the linear estimate's constants (or as configured)."""
    ff: Feedforward | None
    """The windowed SysId estimate (None: too few sliding samples)."""
    ls: LeastSquares | None
    """SysId's own least-squares model (None: it could not be fitted)."""


def linear_start(
    p0: VehicleParams, runs: Sequence[Series], progress: Callable[[str], None]
) -> tuple[VehicleParams, Feedforward | None]:
    """:func:`start_model`, saying what it found."""
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


def least_squares_stage(
    p0: VehicleParams, est: Sequence[Series], progress: Callable[[str], None]
) -> LinearStart:
    """Stage 2 of the diagnosis: the linear estimate on the estimation runs ``est`` (the
    seed fit's start) and SysId's least-squares model (a start, and the bar the
    extended model must clear)."""
    p_lin, ff = linear_start(p0, est, progress)
    return LinearStart(p_lin, ff, least_squares_model(p0, est))
