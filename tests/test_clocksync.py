"""The predecessor's clock from one-way stamps (truckd/control/clocksync.py)."""

from __future__ import annotations

import math
import random

import pytest

from truckd.control.clocksync import ClockEstimator


def _feed(
    est: ClockEstimator,
    rng: random.Random,
    offset: float,
    drift: float,
    t0: float,
    t1: float,
    delay: tuple[float, float] = (0.0, 0.05),
    loss: float = 0.3,
    period: float = 0.01,
) -> None:
    """Messages sent every ``period`` of the sender's clock from t0 to t1, each delayed by
    a draw in ``delay`` (reordered when draws differ by more than a period), ``loss``
    lost; the receiver's clock is ``s + offset + drift s``."""
    out: list[tuple[float, float]] = []
    for k in range(round((t1 - t0) / period)):
        s = t0 + k * period
        if rng.random() < loss:
            continue
        out.append((s + offset + drift * s + rng.uniform(*delay), s))
    out.sort()  # arrival order
    for arrived, sent in out:
        est.observe(sent, arrived)


@pytest.mark.parametrize("seed", range(6))
def test_offset_and_drift_are_found_from_lossy_reordered_messages(seed: int) -> None:
    rng = random.Random(seed)
    offset = rng.uniform(-2.0, 2.0)
    drift = rng.choice([-1.0, 1.0]) * 1e-4  # 100 ppm
    t0 = rng.uniform(0.0, 1e5)  # the sender's clock: any epoch
    est = ClockEstimator()
    _feed(est, rng, offset, drift, t0, t0 + 60.0)
    assert est.estimate is not None
    assert abs(est.estimate.drift - drift) < 2.5e-5, est.estimate
    for s in (t0 + 59.9, t0 + 61.0):  # now and a second ahead
        assert abs(est.to_own(s) - (s + offset + drift * s)) < 0.003


def test_without_the_drift_the_error_grows_with_time() -> None:
    """100 ppm over a 60 s window is 6 ms: the drift estimate keeps the mapping within a
    few ms of the truth 30 s past the window where a constant offset is 9 ms off."""
    rng = random.Random(7)
    est = ClockEstimator()
    _feed(est, rng, 1.5, 1e-4, 0.0, 60.0)
    assert est.estimate is not None
    s = 90.0
    truth = s + 1.5 + 1e-4 * s
    assert abs(est.to_own(s) - truth) < 0.003
    flat = s + est.estimate.offset + est.estimate.drift * (60.0 - est.estimate.ref)
    assert abs(flat - truth) > 0.002


def test_a_constant_delay_is_counted_in_the_offset() -> None:
    """One-way stamps cannot tell offset from the smallest delay (module docstring)."""
    est = ClockEstimator()
    _feed(est, random.Random(1), -0.7, 0.0, 0.0, 10.0, delay=(0.02, 0.02), loss=0.0)
    assert est.to_own(5.0) == pytest.approx(5.0 - 0.7 + 0.02, abs=1e-6)


def test_a_clock_step_restarts_the_estimate() -> None:
    est = ClockEstimator()
    rng = random.Random(2)
    _feed(est, rng, 0.5, 0.0, 0.0, 20.0)
    _feed(est, rng, -1.5, 0.0, 20.0, 30.0)  # the receiver's clock stepped back 2 s
    assert est.steps == 1
    assert abs(est.to_own(29.0) - (29.0 - 1.5)) < 0.003
    _feed(est, rng, 0.5, 0.0, 30.0, 40.0)  # and forward again: after step_count samples
    assert est.steps == 2
    assert abs(est.to_own(39.0) - (39.0 + 0.5)) < 0.003


def test_one_very_late_message_is_not_a_step() -> None:
    est = ClockEstimator()
    _feed(est, random.Random(3), 0.2, 0.0, 0.0, 10.0)
    est.observe(10.0, 10.0 + 0.2 + 3.0)  # 3 s in a queue somewhere
    assert est.steps == 0
    assert abs(est.to_own(10.0) - 10.2) < 0.003


def test_nothing_before_the_first_message_and_bad_input() -> None:
    est = ClockEstimator()
    assert est.estimate is None and math.isnan(est.to_own(1.0))
    est.observe(math.nan, 1.0)
    assert est.estimate is None
    with pytest.raises(ValueError):
        ClockEstimator(bucket_s=0.0)
