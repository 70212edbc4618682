"""Logs prepared for fitting: checks that a log can support a fit, splits, chunks.

Voltage-input logs (``t, u, v`` and optional ``i``) and force-input logs (``t, F`` and
``v`` or ``x``) are turned into plain arrays (SI).  A log that cannot support a fit (too
short, constant input, no motion) raises :class:`truckd.errors.InputError` naming it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.errors import InputError
from truckd.logfile import Log, require_io

Array = NDArray[np.float64]

HISTORY_S = 0.6
"""Seconds of inputs kept before a chunk: covers the largest input delay fitted."""

MIN_SAMPLES = 200
"""Fewer samples than this cannot determine the seed model's parameters."""


@dataclass(frozen=True)
class Series:
    """One contiguous stretch of a log (SI).

    ``inp`` the input (voltage V, or force N), ``v`` measured speed (m/s), ``i`` motor
    current (A) or None, ``x`` position (m) or None.
    """

    t: Array
    inp: Array
    v: Array
    i: Array | None = None
    x: Array | None = None
    hist_t: Array | None = None
    """Times (s) of the inputs before ``t[0]`` (a chunk's history; they may still act)."""
    hist_inp: Array | None = None

    def __len__(self) -> int:
        return len(self.t)

    def slice(self, lo: int, hi: int) -> Series:
        """Samples ``lo:hi``, with up to :data:`HISTORY_S` of earlier inputs as history."""
        h0 = lo
        if lo > 0:
            h0 = int(np.searchsorted(self.t, self.t[lo] - HISTORY_S, "left"))
        return Series(
            t=self.t[lo:hi],
            inp=self.inp[lo:hi],
            v=self.v[lo:hi],
            i=None if self.i is None else self.i[lo:hi],
            x=None if self.x is None else self.x[lo:hi],
            hist_t=self.t[h0:lo] if lo > 0 else None,
            hist_inp=self.inp[h0:lo] if lo > 0 else None,
        )


def speed_from_position(t: Array, x: Array) -> Array:
    """Speed (m/s) from a position record: zero-phase low-pass, central differences."""
    from scipy.signal import butter, filtfilt

    h = float(np.median(np.diff(t)))
    fs = 1.0 / h
    cutoff = min(0.1 * fs, 100.0)
    b, a = butter(4, cutoff / (0.5 * fs))
    xf = filtfilt(b, a, x) if len(x) > 30 else x
    return np.asarray(np.gradient(xf, t), float)


def series_from_log(log: Log) -> Series:
    """The log's input/output columns as a :class:`Series`, checked for a fit."""
    require_io(log)
    t = log["t"]
    if log.input_kind == "voltage":
        inp = log["u"]
        v = log["v"]
    else:
        inp = log["F"]
        v = log["v"] if "v" in log else speed_from_position(t, log["x"])
    s = Series(
        t=t,
        inp=inp,
        v=v,
        i=log.columns.get("i"),
        x=log.columns.get("x"),
    )
    check_excitation(s, log.source, log.input_kind)
    return s


def check_excitation(s: Series, source: str, kind: str) -> None:
    """Raise :class:`InputError` when the data cannot support a fit."""
    name = "u" if kind == "voltage" else "F"
    if len(s) < MIN_SAMPLES:
        raise InputError(
            f"{source}: only {len(s)} samples; a fit needs at least {MIN_SAMPLES} "
            "(several seconds of varied input)"
        )
    span = float(np.ptp(s.inp))
    if span <= 1e-9 * max(1.0, float(np.max(np.abs(s.inp)))):
        raise InputError(
            f"{source}: column '{name}' is constant ({float(s.inp[0])!r}); a fit needs an "
            "input that varies (steps, ramps or random levels)"
        )
    levels = np.unique(np.round(s.inp, 9))
    if len(levels) < 3:
        raise InputError(
            f"{source}: column '{name}' takes only {len(levels)} values; a fit needs at "
            "least 3 different input levels"
        )
    vmax = float(np.max(np.abs(s.v)))
    if vmax <= 0.0 or float(np.ptp(s.v)) < 1e-6:
        raise InputError(
            f"{source}: column 'v' never changes: the log shows no motion to fit (no excitation)"
        )
    if not np.all(np.isfinite(s.v)):
        raise InputError(f"{source}: speed is not finite everywhere")


def noise_std(y: Array) -> float:
    """Robust white-noise level of a smooth signal: MAD of its second difference."""
    if len(y) < 5:
        return 0.0
    d2 = np.diff(y, 2)
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return mad / 0.6745 / float(np.sqrt(6.0))


def initial_speed(v: Array) -> float:
    """Speed to start a free run from: the first sample, or 0 (at rest) when that is
    within the measurement noise (a noisy 0 would start the model sliding)."""
    m = float(v[0])
    return 0.0 if abs(m) < 3.0 * noise_std(v[:300]) else m


def split(s: Series, fraction: float = 0.7) -> tuple[Series, Series]:
    """Estimation (first ``fraction``) and validation (rest) parts of one log."""
    k = int(len(s) * fraction)
    return s.slice(0, k), s.slice(k, len(s))


def chunks(s: Series, budget: int, pieces: int = 4) -> list[Series]:
    """At most ``budget`` samples as ``pieces`` evenly spread contiguous chunks.

    Short logs are returned whole.  Each chunk is simulated from its own measured start.
    """
    n = len(s)
    if n <= budget:
        return [s]
    size = budget // pieces
    starts = np.linspace(0, n - size, pieces).astype(int)
    return [s.slice(int(a), int(a) + size) for a in starts]
