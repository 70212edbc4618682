"""Timelines from a kept layout (truckd.ident.timing) are the reference's arrays, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from truckd.ident import ckernel, fastsim
from truckd.ident.freerun import Timeline, merge_equal, timeline
from truckd.ident.timing import layout_of, merged, shifted


def _series(rng: np.random.Generator, jitter: bool, hist: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample instants (100 Hz, jittered or not) and the command instants with ``hist``
    earlier ones."""
    n = 300
    h = np.full(n + hist - 1, 0.01)
    if jitter:
        h *= rng.uniform(0.5, 1.5, len(h))
    t_all = 3.0 + np.concatenate([[0.0], np.cumsum(h)])
    return t_all[hist:], t_all


def _inputs(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-command inputs held over a few commands (what the merge joins)."""
    levels = rng.choice([-1.0, 0.0, 0.5, 2.0], size=m)
    held = np.repeat(levels, rng.integers(1, 6, size=m))[:m]
    return 3.0 * held, 1.0 + 0.0 * held


def _same(x: Timeline, y: Timeline) -> bool:
    return (
        np.array_equal(x.dt, y.dt)
        and np.array_equal(x.cmd, y.cmd)
        and np.array_equal(x.sample_end, y.sample_end)
        and x.dt.dtype == y.dt.dtype
        and x.cmd.dtype == y.cmd.dtype
        and x.sample_end.dtype == y.sample_end.dtype
    )


@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("hist", [0, 40])
def test_a_timeline_from_a_layout_is_the_reference(jitter: bool, hist: int) -> None:
    rng = np.random.default_rng(11 + hist + int(jitter))
    t, t_cmd = _series(rng, jitter, hist)
    a, b = _inputs(rng, len(t_cmd))
    first = layout_of(t, 4.7e-4, t_cmd)
    assert first is not None
    tl0, lay = first
    assert _same(tl0, timeline(t, 4.7e-4, hist, t_cmd))
    reused = 0
    # Small lags (the order kept), delays across samples (order changes), exact multiples
    # of the sample (ties, which the layout refuses).
    delays = [*rng.uniform(1e-4, 2e-3, 30), *rng.uniform(0.0, 0.2, 30), 0.01, 0.03, 0.05]
    t_hist = t_cmd[:hist] if hist else None  # one array, as a series holds it: the cache's key
    for d in delays:
        ref = timeline(t, float(d), hist, t_cmd)
        tl = shifted(lay, t, float(d), t_cmd)
        if tl is not None:
            reused += 1
            assert _same(tl, ref)
            assert _same(merged(tl, lay, a, b), merge_equal(ref, a, b))
        made = layout_of(t, float(d), t_cmd)
        if made is not None:
            assert _same(made[0], ref)
            assert _same(merged(made[0], made[1], a, b), merge_equal(ref, a, b))
        # What the simulator uses, with its cache: always the reference.
        got = fastsim._merged_timeline(t, t_hist, float(d), hist, t_cmd, a, b)
        assert _same(got, merge_equal(ref, a, b))
    assert reused >= 25  # the small lags keep the order (the case worth keeping)


def test_equal_inputs_merge_and_nan_never_does() -> None:
    t = np.arange(50) * 0.01
    a = np.ones(50)
    b = np.ones(50)
    made = layout_of(t, 1e-3, t)
    assert made is not None
    tl, lay = made
    all_equal = merged(tl, lay, a, b)
    assert len(all_equal.dt) < len(tl.dt)
    assert _same(all_equal, merge_equal(tl, a, b))
    a_nan = np.full(50, np.nan)
    assert _same(merged(tl, lay, a_nan, b), merge_equal(tl, a_nan, b))
    assert len(merged(tl, lay, a_nan, b).dt) == len(tl.dt)
    # A different pattern on the same layout: its own merge.
    a2 = a.copy()
    a2[::2] = 2.0
    assert _same(merged(tl, lay, a2, b), merge_equal(tl, a2, b))


@pytest.mark.parametrize("jitter", [False, True])
@pytest.mark.parametrize("hist", [0, 40])
def test_the_c_kernel_shifts_and_merges_as_numpy(jitter: bool, hist: int) -> None:
    """``ckernel.shift_merge`` (one pass in C) is ``merged(shifted(...))`` bit for bit,
    and refuses the delays whose order the layout does not hold, as ``shifted`` does."""
    assert ckernel.available(), f"{ckernel.LIBRARY} missing: run `make firmware`"
    rng = np.random.default_rng(29 + hist + int(jitter))
    t, t_cmd = _series(rng, jitter, hist)
    a, b = _inputs(rng, len(t_cmd))
    made = layout_of(t, 4.7e-4, t_cmd)
    assert made is not None
    lay = made[1]
    kept = refused = 0
    for d in [*rng.uniform(1e-4, 2e-3, 30), *rng.uniform(0.0, 0.2, 20), 0.01, 0.03]:
        tl = shifted(lay, t, float(d), t_cmd)
        got = ckernel.shift_merge(
            t, t_cmd, float(d), lay.first, lay.stop, lay.order, lay.eps, lay.cmd,
            lay.sample_end, a, b,
        )  # fmt: skip
        if tl is None:
            assert got is None, f"delay {d}: the C pass kept an order numpy refuses"
            refused += 1
            continue
        assert got is not None, f"delay {d}: the C pass refused an order numpy keeps"
        assert _same(Timeline(*got), merged(tl, lay, a, b))
        kept += 1
    assert kept >= 25 and refused >= 5
