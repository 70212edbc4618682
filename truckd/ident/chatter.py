"""Stretches where the measured speed swings fast while the command holds still.

A drivetrain driven by a steady voltage settles to a steady speed: its speed follows the
command through the mechanical time constant and cannot swing faster on its own.  When
the logged speed does (wheels that slip and grip, as a robot turning in place scrubs and
hops; a loose coupling or sensor; the motor controller's own loop), no model of the
drivetrain follows it, and the fit pays for it.  :func:`chatter_spans` finds those
stretches, :func:`without_chatter` cuts them out of the runs before any fit, and
:func:`chatter_note` says where they were and what the model fits with them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from truckd.ident.data import MIN_RUN, Array, Series

TREND_S = 0.2
"""The speed's local trend is its centred moving median over this long (s): what a
drivetrain's speed can do between two samples at most this far apart."""
ROUGH_NOISE = 6.0
"""A local RMS about the trend of this many noise levels ..."""
ROUGH_TOP = 0.05
"""... and at least this share of the run's top speed (a grid's or a wheel's wobble at a
steady speed is far less) ..."""
HELD_SHARE = 0.05
"""... while the command moves by less than this share of its range within the trend's
window ..."""
MIN_SPAN_S = 0.5
"""... for at least this long (s) is chatter: a step's knee is rough for about a
trend's window only."""
MIN_WINDOW = 5
"""Fewest samples in the trend's window."""
MOVING_SHARE = 0.1
"""The noise level is measured where the speed is above this share of its largest."""


@dataclass(frozen=True)
class ChatterSpan:
    """One stretch of chatter in run ``run`` (0-based), from ``start`` to ``end`` (s from
    the run's first sample), the speed's RMS about its trend there ``rms`` (m/s)."""

    run: int
    start: float
    end: float
    rms: float
    first: int
    """Index of the stretch's first sample in the run."""
    stop: int
    """Index one past its last sample."""


BLOCK = 1 << 16
"""Windows reduced at a time (the memory of a long log's windows stays a few MB)."""


def _moving(a: Array, w: int, reduce: Callable[..., Array]) -> Array:
    """``reduce(windows, axis=1)`` over the windows of ``w`` samples centred on each
    sample of ``a`` (edges repeated), :data:`BLOCK` windows at a time."""
    h = w // 2
    padded = np.concatenate([np.full(h, a[0]), a, np.full(w - 1 - h, a[-1])])
    windows = sliding_window_view(padded, w)
    return np.concatenate([reduce(windows[k : k + BLOCK], axis=1) for k in range(0, len(a), BLOCK)])


def _local_noise(v: Array, w: int) -> float:
    """The speed sensor's noise level (m/s) in ``v`` where it moves: the lower quartile,
    over the samples in motion, of the robust noise level (MAD of the second difference)
    in the ``w`` samples around each.  A sensor's noise often grows with speed, and chatter
    over part of a run must not raise the level it is measured against."""
    d2 = np.abs(np.diff(v, 2))
    if len(d2) < w:
        return 0.0
    local = _moving(d2, w, np.median) / 0.6745 / float(np.sqrt(6.0))
    speed = np.abs(v[1:-1])
    moving = speed > MOVING_SHARE * float(np.max(speed))
    return float(np.percentile(local[moving], 25.0)) if np.any(moving) else 0.0


def _mask(r: Series) -> tuple[NDArray[np.bool_], Array]:
    """Which samples of ``r`` are chatter, and the local RMS about the trend (m/s)."""
    n = len(r)
    none = np.zeros(n, dtype=bool), np.zeros(n)
    if n < 3 * MIN_WINDOW:
        return none
    dt = float(np.median(np.diff(r.t)))
    if not dt > 0.0:
        return none
    w = max(MIN_WINDOW, round(TREND_S / dt) | 1)
    if n < 3 * w:
        return none
    v = np.asarray(r.v, float)
    resid = v - _moving(v, w, np.median)
    rough = np.sqrt(_moving(resid * resid, w, np.mean))
    thr = max(ROUGH_NOISE * _local_noise(v, w), ROUGH_TOP * float(np.max(np.abs(v))))
    u = np.asarray(r.inp, float)
    u_range = float(np.max(u) - np.min(u))
    held = _moving(u, w, np.ptp) <= HELD_SHARE * u_range
    return (rough > thr) & held & (thr > 0.0), rough


def chatter_spans(runs: Sequence[Series]) -> list[ChatterSpan]:
    """Every stretch of chatter (module docstring) in ``runs``, run by run, in order."""
    out = []
    for k, r in enumerate(runs):
        bad, rough = _mask(r)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(np.int8), [0]])))
        for a, b in zip(edges[0::2], edges[1::2], strict=True):
            if r.t[b - 1] - r.t[a] >= MIN_SPAN_S:
                rms = float(np.sqrt(np.mean(rough[a:b] ** 2)))
                t0 = float(r.t[0])
                out.append(
                    ChatterSpan(k, float(r.t[a]) - t0, float(r.t[b - 1]) - t0, rms, int(a), int(b))
                )
    return out


def without_chatter(runs: Sequence[Series]) -> tuple[list[Series], list[ChatterSpan]]:
    """``runs`` with each stretch of chatter cut out (each piece after one starts from
    its own measured state, with its history; pieces under :data:`MIN_RUN` samples
    dropped), and the stretches.  Nothing is cut when nothing would be left."""
    spans = chatter_spans(runs)
    if not spans:
        return list(runs), spans
    out: list[Series] = []
    for k, r in enumerate(runs):
        lo = 0
        for s in (s for s in spans if s.run == k):
            if s.first - lo >= MIN_RUN:
                out.append(r.slice(lo, s.first))
            lo = s.stop
        if len(r) - lo >= MIN_RUN:
            out.append(r.slice(lo, len(r)) if lo else r)
    if not out:
        return list(runs), []
    return out, spans


def chatter_where(spans: Sequence[ChatterSpan]) -> str:
    """``run 2 0.10-4.70 s (RMS 2.03 m/s)``, for up to three stretches."""
    text = "; ".join(
        f"run {s.run + 1} {s.start:.2f}-{s.end:.2f} s (RMS {s.rms:.3g} m/s)" for s in spans[:3]
    )
    return text + (f" and {len(spans) - 3} more" if len(spans) > 3 else "")


def chatter_note(
    spans: Sequence[ChatterSpan],
    spans_val: Sequence[ChatterSpan],
    fit_percent: float,
    fit_with: float,
) -> str:
    """The note naming the chatter left out of the data (``spans``) and the validation
    data (``spans_val``), with the model's fit on the report data without it
    (``fit_percent``) and with it (``fit_with``), both %."""
    total = sum(s.end - s.start for s in [*spans, *spans_val])
    where = [
        *([f"in the data: {chatter_where(spans)}"] if spans else []),
        *([f"in the validation data: {chatter_where(spans_val)}"] if spans_val else []),
    ]
    return (
        f"chatter: the speed swings fast at a steady command for {total:.2f} s "
        f"({'; '.join(where)}; times from each run's start): wheels that slip and grip "
        "(a robot turning in place scrubs and hops), a loose coupling or sensor, or the "
        "motor controller's own loop. No drivetrain model follows it: left out of the fit "
        f"and the figures. The model fits {fit_percent:.1f} % without it, {fit_with:.1f} % "
        "with it"
    )


def spans_json(spans: Sequence[ChatterSpan], data: str) -> list[dict[str, float | int | str]]:
    """The ``chatter`` JSON entries (docs/reference.md section 4) of ``spans`` of ``data``
    (``log`` or ``validation``): run (1-based), from_s, to_s, rms (m/s)."""
    return [
        {"data": data, "run": s.run + 1, "from_s": s.start, "to_s": s.end, "rms": s.rms}
        for s in spans
    ]
