"""Timelines of one series under many delays, sorted once.

:func:`truckd.ident.freerun.timeline` sorts a series' sample instants together with
its commands' action instants (each command ``delay`` s after it was issued).  In a fit
the delay (the input delay plus the electrical lag ``L_m/R``, which moves with the
motor's parameters) changes at nearly every evaluation, while the order of those
instants does not.  A :class:`Layout` keeps that order (found by a sort once); a new
delay then takes the instants in the kept order and only checks that they are still
strictly increasing, more than the tie tolerance apart (else: a full
:func:`~truckd.ident.freerun.timeline`).  Which split sub-intervals
:func:`~truckd.ident.freerun.merge_equal` joins depends only on which neighbouring
commands have equal inputs: each such pattern's merged layout is kept too.

Both give the same arrays, bit for bit, as :func:`~truckd.ident.freerun.timeline` and
:func:`~truckd.ident.freerun.merge_equal` (``tests/test_ident_timing.py``): when the
instants are more than the tolerance apart, the stable sort's order is the only
increasing one, no tie is dropped, the command active over each sub-interval is the
last one whose action instant is among the bounds before it, and the durations are the
same differences of the same numbers.  Pure numerics.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from truckd.ident.freerun import Timeline

Array = NDArray[np.float64]
Ints = NDArray[np.int64]

MERGES_KEPT = 8
"""Merge patterns kept per layout (a fit sees one or two: which commands are equal)."""


@dataclass(frozen=True)
class _Merge:
    """One merge pattern's result: where the merged sub-intervals start (in the
    unmerged ones) and their commands and sample ends."""

    starts: Ints
    cmd: Ints
    sample_end: Ints


@dataclass(frozen=True)
class Layout:
    """The order of a series' instants under a delay without ties (see module
    docstring)."""

    first: int
    """First command whose action instant lies inside the series (strictly)."""
    stop: int
    """One past the last one."""
    order: Ints
    """Stable sort order of the sample instants followed by those action instants."""
    eps: float
    """Tie tolerance (s) of :func:`truckd.ident.freerun.timeline`."""
    cmd: Ints
    """Command active over each sub-interval (-1: none yet)."""
    sample_end: Ints
    """Sample ending each sub-interval (-1: an action instant ends it)."""
    split: Ints
    """Sub-intervals ended by an action instant, not the last one."""
    left: Ints
    """Their command (0 where none)."""
    right: Ints
    """The next sub-interval's command (0 where none)."""
    both: NDArray[np.bool_]
    """Both commands exist."""
    merges: dict[bytes, _Merge] = field(default_factory=dict, compare=False)
    """Merged layouts by pattern (which splits join)."""


def layout_of(t: Array, delay: float, t_cmd: Array) -> tuple[Timeline, Layout] | None:
    """The timeline of commands issued at ``t_cmd`` (s, increasing) acting ``delay`` s
    (> 0) later over the sample instants ``t`` (s), and its layout; None when two instants
    lie within the tolerance (or the commands are not increasing): then
    :func:`truckd.ident.freerun.timeline` resolves the ties."""
    n = len(t)
    eps = 1e-12 * max(1.0, abs(float(t[-1])))
    if n < 2 or not delay > 0.0 or not bool(np.all(np.diff(t_cmd) > 0.0)):
        return None
    act = t_cmd + delay
    inside = np.flatnonzero((act > t[0]) & (act < t[-1]))
    if inside.size == 0:
        return None
    first, stop = int(inside[0]), int(inside[-1]) + 1
    bounds = np.concatenate([t, act[first:stop]])
    order = np.argsort(bounds, kind="stable")
    bounds = bounds[order]
    dt = np.diff(bounds)
    if not bool(np.all(dt > eps)):
        return None
    is_sample = order < n
    cmd = (np.searchsorted(act, bounds[:-1] + eps, "right") - 1).astype(np.int64)
    sample_idx = np.cumsum(is_sample) - 1
    sample_end = np.where(is_sample[1:], sample_idx[1:], -1).astype(np.int64)
    split = np.flatnonzero(sample_end[:-1] < 0)
    left, right = cmd[split], cmd[split + 1]
    lay = Layout(
        first=first,
        stop=stop,
        order=order.astype(np.int64),
        eps=eps,
        cmd=cmd,
        sample_end=sample_end,
        split=split,
        left=np.maximum(left, 0),
        right=np.maximum(right, 0),
        both=(left >= 0) & (right >= 0),
    )
    return Timeline(dt=dt, cmd=cmd, sample_end=sample_end), lay


def shifted(lay: Layout, t: Array, delay: float, t_cmd: Array) -> Timeline | None:
    """The timeline under another ``delay`` (s) in the order of ``lay`` (made for the
    same sample instants ``t`` and command instants ``t_cmd``, s); None when that order
    does not hold for it."""
    act = t_cmd + delay
    t0, t1 = t[0], t[-1]
    if not (act[lay.first] > t0 and act[lay.stop - 1] < t1):
        return None
    if lay.first > 0 and not act[lay.first - 1] <= t0:
        return None
    if lay.stop < len(act) and not act[lay.stop] >= t1:
        return None
    bounds = np.concatenate([t, act[lay.first : lay.stop]])[lay.order]
    dt = np.diff(bounds)
    if not float(np.min(dt)) > lay.eps:
        return None
    return Timeline(dt=dt, cmd=lay.cmd, sample_end=lay.sample_end)


def merged(tl: Timeline, lay: Layout, a: Array, b: Array) -> Timeline:
    """:func:`truckd.ident.freerun.merge_equal` of ``tl`` (a timeline in the layout
    ``lay``) for the per-command inputs ``a`` and ``b`` (the free run's two input terms, in
    its units; only their equality counts): neighbouring sub-intervals whose commands have
    equal inputs are joined."""
    same = lay.both & (a[lay.left] == a[lay.right]) & (b[lay.left] == b[lay.right])
    if not bool(same.any()):
        return tl
    key = np.packbits(same).tobytes()
    m = lay.merges.get(key)
    if m is None:
        keep = np.ones(len(lay.cmd), bool)
        keep[lay.split[same]] = False
        starts = np.concatenate([[0], np.flatnonzero(keep)[:-1] + 1])
        m = _Merge(starts=starts, cmd=lay.cmd[keep], sample_end=lay.sample_end[keep])
        if len(lay.merges) >= MERGES_KEPT:
            del lay.merges[next(iter(lay.merges))]
        lay.merges[key] = m
    return Timeline(dt=np.add.reduceat(tl.dt, m.starts), cmd=m.cmd, sample_end=m.sample_end)
