"""Residual analysis: whiteness, correlation with the input, structure against signals.

For a model that explains the data, the free-run residual ``y - y_sim`` is the
measurement noise: white and uncorrelated with the input.  The sample autocorrelation
of white noise of length N lies within ``+-z/sqrt(N)`` (z = 2.58 for 99 %), and so does
its cross-correlation with any input.  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

Z99 = 2.576
"""Two-sided 99 % normal quantile for the confidence bands."""


FFT_LEN = 1 << 16
"""Samples per FFT of the lagged sums: a long record is summed in blocks of this length
(minus the lags), so memory stays a few MB whatever its length."""


def lagged_sums(a: Array, b: Array, max_lag: int) -> Array:
    """``sum_k a[k] b[k - lag]`` for lags ``-max_lag..max_lag`` (b zero outside it).

    Summed over blocks of ``a``, each correlated by FFT with the stretch of ``b`` it
    meets: the same sums as one FFT of twice the record's length, in memory that does
    not grow with it."""
    n, lags = len(a), max_lag
    need = n + 2 * lags
    if need <= FFT_LEN:  # a short record: one FFT holds it
        nfft = 1 << max(1, (need - 1).bit_length())
    else:  # blocks at least as long as their overlap
        nfft = max(FFT_LEN, 1 << (4 * lags + 1).bit_length())
    step = nfft - 2 * lags
    out = np.zeros(2 * lags + 1)
    seg = np.empty(nfft)
    for s in range(0, n, step):
        e = min(n, s + step)
        lo, hi = s - lags, e + lags  # b[lo:hi], zero where outside
        seg[:] = 0.0
        seg[max(0, -lo) : max(0, -lo) + min(hi, n) - max(lo, 0)] = b[max(lo, 0) : min(hi, n)]
        c = np.fft.irfft(np.fft.rfft(seg) * np.conj(np.fft.rfft(a[s:e], nfft)), nfft)
        out += c[2 * lags :: -1]  # c[d] pairs a[k] with b[k + d - lags]: lag = lags - d
    return out


def autocorr(r: Array, max_lag: int) -> Array:
    """Normalised autocorrelation of r at lags 0..max_lag."""
    r = r - np.mean(r)
    den = float(r @ r)
    if den == 0.0:
        return np.zeros(max_lag + 1)
    return np.asarray(lagged_sums(r, r, max_lag)[max_lag:] / den, float)


def crosscorr(r: Array, u: Array, max_lag: int) -> Array:
    """Normalised cross-correlation of r[k] with u[k - lag], lags -max_lag..max_lag."""
    r = r - np.mean(r)
    u = u - np.mean(u)
    den = float(np.sqrt((r @ r) * (u @ u)))
    if den == 0.0:
        return np.zeros(2 * max_lag + 1)
    return np.asarray(lagged_sums(r, u, max_lag) / den, float)


def band(n: int) -> float:
    """99 % confidence half-width of a sample correlation of white noise, length n."""
    return Z99 / float(np.sqrt(max(n, 1)))


@dataclass(frozen=True)
class Binned:
    """Mean residual (and its 99 % band) in bins of another signal."""

    centers: Array
    mean: Array
    half_width: Array


def binned(x: Array, r: Array, bins: int = 20) -> Binned:
    """Residual against a signal: mean per equal-count bin with a 99 % band."""
    order = np.argsort(x)
    groups = np.array_split(order, min(bins, max(len(x) // 5, 1)))
    c, m, hw = [], [], []
    for g in groups:
        if len(g) == 0:
            continue
        c.append(float(np.mean(x[g])))
        m.append(float(np.mean(r[g])))
        hw.append(Z99 * float(np.std(r[g])) / np.sqrt(len(g)))
    return Binned(np.array(c), np.array(m), np.array(hw))


@dataclass(frozen=True)
class Whiteness:
    """Summary of the residual tests on one record."""

    rms: float
    noise: float
    """Measurement noise level estimated from the data (m/s)."""
    structure: float
    """RMS of the residual beyond the noise, ``sqrt(max(rms^2 - noise^2, 0))``."""
    acf_outside: float
    """Fraction of lags 1..L with |autocorrelation| beyond the 99 % band."""
    ccf_outside: float
    """Fraction of lags -L..L with |cross-correlation with the input| beyond the band."""


def whiteness(r: Array, u: Array, noise: float, max_lag: int) -> Whiteness:
    """Residual tests used to decide whether structure remains."""
    n = len(r)
    lag = max(1, min(max_lag, n // 4))
    b = band(n)
    acf = autocorr(r, lag)[1:]
    ccf = crosscorr(r, u, lag)
    rms = float(np.sqrt(np.mean(r**2)))
    return Whiteness(
        rms=rms,
        noise=noise,
        structure=float(np.sqrt(max(rms * rms - noise * noise, 0.0))),
        acf_outside=float(np.mean(np.abs(acf) > b)),
        ccf_outside=float(np.mean(np.abs(ccf) > b)),
    )


LOOKS_MIN = 0.2
"""A residual is said to look like a signal when their correlation exceeds this (and the
white-noise band)."""


def looks_like(r: Array, signals: Iterable[tuple[str, Array]]) -> dict[str, float]:
    """Correlation coefficient of the residual ``r`` with each signal (speed,
    acceleration, sign of the command, time, position...), for those beyond
    :data:`LOOKS_MIN` and the 99 % band, strongest first."""
    out: dict[str, float] = {}
    b = band(len(r))
    rc = r - np.mean(r)
    nr = float(np.linalg.norm(rc))
    if nr == 0.0:
        return out
    for name, x in signals:
        xc = np.asarray(x, float) - np.mean(x)
        nx = float(np.linalg.norm(xc))
        if nx == 0.0 or len(xc) != len(rc):
            continue
        c = float(rc @ xc) / (nr * nx)
        if abs(c) > max(LOOKS_MIN, b):
            out[name] = c
    return dict(sorted(out.items(), key=lambda kv: -abs(kv[1])))
