"""Logs prepared for fitting: checks that a log can support a fit, splits, chunks.

Voltage-input logs (``t, u, v`` and optional ``i``) and force-input logs (``t, F`` and
``v`` or ``x``) are turned into plain arrays (SI).  A log that cannot support a fit (too
short, constant input, no motion) raises :class:`truckd.errors.InputError` naming it.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.errors import InputError
from truckd.logfile import Log, require_io

Array = NDArray[np.float64]

HISTORY_S = 0.6
"""Seconds of inputs kept before a chunk: covers the largest input delay fitted."""

MIN_SAMPLES = 50
"""Fewer samples (over all runs) than this cannot determine the seed model's parameters."""


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
    origin: Series | None = None
    """The whole run this stretch was cut from (None: it starts the run), which a winding
    heating over the run (``resistance_drift``) is simulated over up to ``offset``."""
    offset: int = 0
    """Index of ``t[0]`` in ``origin``."""

    def __len__(self) -> int:
        return len(self.t)

    @functools.cached_property
    def fresh(self) -> NDArray[np.bool_]:
        """:func:`fresh_mask` of ``v``: the samples with a new speed reading."""
        return fresh_mask(self.v)

    @functools.cached_property
    def all_fresh(self) -> bool:
        """Whether every sample holds a new speed reading (no sample and hold)."""
        return bool(self.fresh.all())

    @functools.cached_property
    def start_speed(self) -> float:
        """:func:`initial_speed` of ``v`` (computed once: every free run starts there)."""
        return initial_speed(self.v)

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
            origin=(self.origin or self) if self.offset + lo > 0 else None,
            offset=self.offset + lo,
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


GAP_FACTOR = 10.0
"""A time step more than this many median steps long is a pause: the log splits there."""

MIN_RUN = 10
"""Runs shorter than this (samples) between pauses are dropped (nothing to simulate)."""


def series_from_log(log: Log) -> Series:
    """The log's input/output columns as one :class:`Series`, checked for a fit."""
    s = _series(log)
    check_excitation([s], log.source, log.input_kind)
    return s


def _series(log: Log) -> Series:
    require_io(log)
    # Times from the log's first sample: a clock's epoch (Unix time, 1.7e9 s) would leave
    # float64 a resolution of 0.2 us, and every lag, delay and interpolation rounding to it.
    t = log["t"] - log["t"][0] if len(log) else log["t"]
    if log.input_kind == "voltage":
        inp = log["u"]
        v = log["v"]
    else:
        inp = log["F"]
        v = log["v"] if "v" in log else speed_from_position(t, log["x"])
    return Series(t=t, inp=inp, v=v, i=log.columns.get("i"), x=log.columns.get("x"))


def gap_threshold(t: Array, gap: float | None = None) -> float:
    """Time step (s) above which a log is split: ``gap``, else ``GAP_FACTOR`` median steps."""
    if gap is not None:
        return float(gap)
    if len(t) < 2:
        return float("inf")
    return GAP_FACTOR * float(np.median(np.diff(t)))


def split_runs(s: Series, gap: float | None = None) -> list[Series]:
    """``s`` cut at its pauses (time steps above :func:`gap_threshold`) into runs.

    Each run is simulated from its own measured start (no history crosses a pause).
    Runs shorter than :data:`MIN_RUN` samples are dropped.
    """
    thr = gap_threshold(s.t, gap)
    cuts = np.flatnonzero(np.diff(s.t) > thr) + 1
    edges = [0, *(int(c) for c in cuts), len(s)]
    out = []
    for lo, hi in itertools.pairwise(edges):
        if hi - lo >= MIN_RUN:
            out.append(
                Series(
                    t=s.t[lo:hi],
                    inp=s.inp[lo:hi],
                    v=s.v[lo:hi],
                    i=None if s.i is None else s.i[lo:hi],
                    x=None if s.x is None else s.x[lo:hi],
                )
            )
    return out


def runs_from_logs(logs: Sequence[Log], gap: float | None = None) -> list[Series]:
    """All runs of several logs (one experiment each, split at pauses), checked together.

    Raises :class:`InputError` when the logs mix input kinds, disagree on the current
    column, or together cannot determine anything.
    """
    if not logs:
        raise InputError("no log given")
    kind = logs[0].input_kind
    runs: list[Series] = []
    for log in logs:
        if log.input_kind != kind:
            raise InputError(
                f"{log.source}: line 1: a {log.input_kind}-input log cannot be used with a "
                f"{kind}-input log ({logs[0].source})"
            )
        s = _series(log)
        got = split_runs(s, gap)
        if not got and len(s) < MIN_RUN:
            raise InputError(
                f"{log.source}: {len(s)} sample(s) with distinct times; a run needs at "
                f"least {MIN_RUN}"
            )
        if not got:
            raise InputError(
                f"{log.source}: no stretch of {MIN_RUN} samples without a pause "
                f"(pause = time step above {gap_threshold(s.t, gap):.4g} s; see --gap)"
            )
        runs.extend(got)
    if len({r.i is None for r in runs}) > 1:
        runs = [dataclasses.replace(r, i=None) for r in runs]
    check_excitation(runs, ", ".join(log.source for log in logs), kind)
    return runs


def merged(runs: Sequence[Series]) -> Series:
    """Runs end to end (times shifted to follow each other) for statistics and plots.

    Never simulated as one: the joins are not continuous.
    """
    if len(runs) == 1:
        return runs[0]
    ts = []
    off = 0.0
    for r in runs:
        h = float(np.median(np.diff(r.t))) if len(r) > 1 else 0.01
        ts.append(r.t - r.t[0] + off)
        off = float(ts[-1][-1]) + h
    has_i = all(r.i is not None for r in runs)
    has_x = all(r.x is not None for r in runs)
    return Series(
        t=np.concatenate(ts),
        inp=np.concatenate([r.inp for r in runs]),
        v=np.concatenate([r.v for r in runs]),
        i=np.concatenate([r.i for r in runs if r.i is not None]) if has_i else None,
        x=np.concatenate([r.x for r in runs if r.x is not None]) if has_x else None,
    )


def check_excitation(runs: Sequence[Series], source: str, kind: str) -> None:
    """Raise :class:`InputError` when the runs together determine nothing.

    Every common experiment passes: a single step (from rest or between two levels),
    ramps, random levels, manual driving.  Refused: too few samples, non-finite values,
    no motion beyond the noise.
    """
    n = sum(len(r) for r in runs)
    if n < MIN_SAMPLES:
        raise InputError(
            f"{source}: only {n} samples; a fit needs at least {MIN_SAMPLES} "
            "(a step, a ramp or a few seconds of varied input)"
        )
    name = "u" if kind == "voltage" else "F"
    for r in runs:
        if not np.all(np.isfinite(r.v)):
            raise InputError(f"{source}: speed is not finite everywhere")
        if not np.all(np.isfinite(r.inp)):
            raise InputError(f"{source}: column '{name}' is not finite everywhere")
    v = np.concatenate([r.v for r in runs])
    noise = float(np.mean([noise_std(r.v) for r in runs]))
    if float(np.max(np.abs(v))) <= max(5.0 * noise, 1e-6) or float(np.ptp(v)) < 1e-6:
        raise InputError(
            f"{source}: column 'v' never changes beyond its noise: the log shows no motion "
            "to fit (no excitation)"
        )
    inp = np.concatenate([r.inp for r in runs])
    if not np.any(inp != 0.0):
        raise InputError(
            f"{source}: column '{name}' is 0 throughout: nothing drives the truck, so no "
            "parameter of the drive can be determined"
        )


HELD = 0.3
"""A signal whose sample-to-sample change is exactly zero this often (and not always) is
sampled and held: a sensor slower than the log."""


PERIODIC = 0.6
"""... and a held signal changes at its median interval (+-1 sample) this often."""


def fresh_mask(y: Array) -> NDArray[np.bool_]:
    """Which samples of ``y`` carry a new reading (all, unless sampled and held:
    :func:`fresh_samples`)."""
    out = np.ones(len(y), dtype=bool)
    if len(y) < 3:
        return out
    changed = np.diff(y) != 0.0
    if 1.0 - float(np.mean(changed)) < HELD or not changed.any():
        return out
    # A sensor slower than the log updates at a steady interval; a coarse speed at rest
    # or at steady state repeats irregularly and is not held (all its samples count),
    # nor is a speed read on a grid that changes by one count at a time (an encoder's
    # speed crossing its counts at a steady acceleration changes at a steady interval).
    if _one_count_at_a_time(y, changed):
        return out
    gaps = np.diff(np.flatnonzero(changed))
    if len(gaps) < 3:
        return out
    k = float(np.median(gaps))
    if k < 2.0 or float(np.mean(np.abs(gaps - k) <= 1.0)) < PERIODIC:
        return out
    out[1:] = changed
    return out


def _one_count_at_a_time(y: Array, changed: NDArray[np.bool_]) -> bool:
    """``y`` is read on a grid (:func:`grid_step`) and :data:`ONE_COUNT` of its changes
    are one step of it."""
    q = grid_step(y)
    if q == 0.0:
        return False
    steps = np.abs(np.diff(y))[changed] / q
    return float(np.mean(np.abs(steps - 1.0) <= GRID_TOL)) >= ONE_COUNT


def fresh_samples(y: Array) -> Array:
    """The samples of ``y`` that carry a new reading: all of them, or for a sampled-and-
    held signal (a speed that updates every 4th sample repeats its value,
    :data:`HELD`) the first sample and each one that differs from the one before."""
    if len(y) < 3:
        return y
    changed = np.diff(y) != 0.0
    held = 1.0 - float(np.mean(changed))
    if held < HELD or not changed.any():
        return y
    return np.asarray(y[np.concatenate([[0], np.flatnonzero(changed) + 1])], float)


def noise_std(y: Array) -> float:
    """Robust white-noise level of a smooth signal: MAD of its second difference, over
    its fresh readings (:func:`fresh_samples`: a held value would give noise 0)."""
    y = fresh_samples(np.asarray(y, float))
    if len(y) < 5:
        return 0.0
    d2 = np.diff(y, 2)
    mad = float(np.median(np.abs(d2 - np.median(d2))))
    return mad / 0.6745 / float(np.sqrt(6.0))


GRID_ON = 0.95
"""A speed whose fresh readings sit this often on multiples of one step (within
:data:`GRID_TOL` of it) is read on a grid: an encoder's counts per sample period."""
GRID_TOL = 0.02
"""... within this share of the step."""
ONE_COUNT = 0.8
"""A speed on a grid whose changes are one step this often crosses its counts: it is
read on the grid, not sampled and held (a held sensor jumps by what moved meanwhile)."""


def grid_step(y: Array) -> float:
    """The step of the grid the speed ``y`` is read on (m/s; an encoder's count over the
    sample period), 0.0 when it is not read on one: the smallest change between its
    fresh readings, when :data:`GRID_ON` of them sit on its multiples."""
    f = fresh_samples(np.asarray(y, float))
    if len(f) < 10:
        return 0.0
    d = np.abs(np.diff(f))
    d = d[d > 1e-9 * max(float(np.max(np.abs(f))), 1e-300)]
    if len(d) < 5:
        return 0.0
    q = float(np.min(d))
    k = (f - f[0]) / q
    if float(np.max(np.abs(k))) > 1e6:  # a fine grid (or none) is no floor worth having
        return 0.0
    on = np.abs(k - np.round(k)) <= GRID_TOL
    return q if float(np.mean(on)) >= GRID_ON else 0.0


def grid_noise(y: Array, q: float, fresh: NDArray[np.bool_]) -> float:
    """White-noise level (m/s) of a speed ``y`` read on a grid of step ``q`` (m/s) over
    its fresh readings ``fresh`` (:func:`fresh_mask`): as :func:`noise_std`, with the
    median of the absolute second differences taken as
    grouped data (classes one step wide, interpolated within its class): those
    differences are multiples of ``q``, and their plain median overstates a noise of
    about one step by up to half."""
    d2 = np.diff(np.asarray(y, float)[fresh], 2)
    if len(d2) < 3:
        return 0.0
    k = np.round(np.abs(d2 - np.median(d2)) / q).astype(int)
    counts = np.bincount(k)
    below = np.concatenate([[0], np.cumsum(counts)[:-1]])
    m = int(np.searchsorted(np.cumsum(counts), len(k) / 2.0))
    lower = max(m - 0.5, 0.0)  # class 0 is [0, q/2): the values are absolute
    width = 0.5 if m == 0 else 1.0
    mad = q * (lower + width * (len(k) / 2.0 - float(below[m])) / float(counts[m]))
    return mad / 0.6745 / float(np.sqrt(6.0))


def ceiling_noise(y: Array, fresh: NDArray[np.bool_]) -> float:
    """The measurement noise's sum of squares (m^2/s^2) over the fresh readings
    ``fresh`` of ``y`` that the ceiling allows for: the white noise (:func:`noise_std`)
    on each reading; on a speed read on a grid of step ``q`` (:func:`grid_step`) its
    noise by :func:`grid_noise`, and at least the rounding's ``q^2 / 12`` on each reading
    off 0 (a grid's second difference is mostly zero, a noise of 0 by the MAD, and a
    truck at rest reads its 0 exactly unless the noise exceeds the rounding)."""
    n = int(fresh.sum())
    q = grid_step(y)
    if q == 0.0:
        return noise_std(y) ** 2 * n
    sigma2, rounding = grid_noise(y, q, fresh) ** 2, q * q / 12.0
    moving = int(np.count_nonzero(y[fresh]))
    at_rest = sigma2 if sigma2 > rounding else noise_std(y) ** 2
    return max(sigma2, rounding) * moving + at_rest * (n - moving)


def fit_ceiling_percent(runs: Sequence[Series], best_fit: float | None = None) -> float | None:
    """The ``fit_percent`` (reference section 4) a model that leaves only the measurement
    noise would reach on ``runs``: ``100 (1 - sqrt(sum_k n_k sigma_k^2) / ||y - mean(y)||)``
    over the fresh readings (:func:`fresh_mask`), ``sigma_k`` run k's noise level
    (m/s) and ``n_k`` its fresh samples (a grid's rounding counted,
    :func:`ceiling_noise`).  No model of the truck can fit the measured speed better
    than its noise lets it (in expectation).  ``best_fit`` (%, the best model's fit on
    the same runs) bounds the noise from above: a speed that changes within a sample
    counts its motion as noise in the second difference, and a model that fits better
    shows the noise is smaller.  None when the speed does not vary."""
    if not runs:
        return None
    masks = [fresh_mask(r.v) for r in runs]
    y = np.concatenate([r.v[m] for r, m in zip(runs, masks, strict=True)])
    den = float(np.linalg.norm(y - np.mean(y)))
    if not den > 0.0:
        return None
    noise = sum(ceiling_noise(r.v, m) for r, m in zip(runs, masks, strict=True))
    ceiling = 100.0 * (1.0 - float(np.sqrt(noise)) / den)
    return ceiling if best_fit is None else max(ceiling, best_fit)


SPIKE_NOISE = 20.0
"""A speed sample this many noise levels off the mean of its two neighbours ..."""
SPIKE_SHARE = 0.1
"""... and this share of the speed's range (5th to 95th percentile) ..."""
SPIKE_AGREE = 0.25
"""... while the neighbours agree within this share of its departure, is a spike: no
truck's speed leaves and comes back in one sample (a sensor's glitch, a dropped bit)."""


def despiked(s: Series) -> tuple[Series, int]:
    """``s`` with each isolated spike of its speed (:data:`SPIKE_NOISE`) replaced by the
    mean of its neighbours, and how many there were (the least squares and the fits
    weigh one wild sample like thousands of good ones)."""
    v = s.v
    if len(v) < 5:
        return s, 0
    mid = 0.5 * (v[:-2] + v[2:])
    dev = np.abs(v[1:-1] - mid)
    lo, hi = np.percentile(v, [5.0, 95.0])
    thr = max(SPIKE_NOISE * noise_std(v), SPIKE_SHARE * float(hi - lo))
    bad = np.flatnonzero((dev > thr) & (np.abs(v[2:] - v[:-2]) < SPIKE_AGREE * dev))
    if not len(bad):
        return s, 0
    out = v.copy()
    out[bad + 1] = mid[bad]
    return dataclasses.replace(s, v=out), len(bad)


def despiked_runs(runs: Sequence[Series], what: str) -> tuple[list[Series], str | None]:
    """:func:`despiked` on every run, and the note saying how many spikes ``what`` (``the
    data``, ``the validation data``) had (None: none)."""
    out, n = [], 0
    for r in runs:
        d, k = despiked(r)
        out.append(d)
        n += k
    if not n:
        return out, None
    return out, (
        f"{n} isolated spike(s) of the speed in {what} (a sample that leaves its "
        "two neighbours by over "
        f"{SPIKE_NOISE:g} noise levels and comes back: a sensor's glitch) replaced by "
        "the mean of their neighbours"
    )


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


def with_position(s: Series) -> Series:
    """``s`` with a position (m): its own ``x`` column, else the speed integrated
    (trapezoid) from 0 at the run's start."""
    if s.x is not None:
        return s
    steps = 0.5 * (s.v[1:] + s.v[:-1]) * np.diff(s.t)
    return dataclasses.replace(s, x=np.concatenate([[0.0], np.cumsum(steps)]))


def chunks_of_runs(runs: Sequence[Series], budget: int, pieces: int = 4) -> list[Series]:
    """At most ``budget`` samples over all runs, shared in proportion to their lengths.

    Each run gets at least one chunk; each chunk starts from its own measured state.
    """
    n = sum(len(r) for r in runs)
    if n <= budget:
        return list(runs)
    out: list[Series] = []
    for r in runs:
        share = max(int(budget * len(r) / n), min(len(r), 50))
        k = max(1, min(pieces, round(pieces * len(runs) * len(r) / n)))
        out.extend(chunks(r, share, k))
    return out


def split_runs_for_validation(
    runs: Sequence[Series], fraction: float = 0.7
) -> tuple[list[Series], list[Series]]:
    """Estimation and validation runs when no validation log is given.

    Several runs: every run is cut at ``fraction`` (the validation part starts from its
    measured state, with its history), so both sides see every experiment.
    """
    est, val = [], []
    for r in runs:
        a, b = split(r, fraction)
        est.append(a)
        if len(b) >= MIN_RUN:
            val.append(b)
    return est, val or est
