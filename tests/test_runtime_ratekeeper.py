"""RateKeeper against a fake clock: drift-free deadlines, skipped periods, statistics."""

from __future__ import annotations

import pytest

from truckd.runtime.ratekeeper import RateKeeper


class FakeClock:
    """Monotonic time that only moves when slept on or advanced by the test."""

    def __init__(self) -> None:
        self.t = 1000.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        assert s > 0
        self.sleeps.append(s)
        self.t += s


def run_cycles(rk: RateKeeper, clk: FakeClock, work: list[float], wake_jitter: float = 0.0) -> None:
    for w in work:
        clk.t += wake_jitter
        rk.begin_cycle()
        clk.t += w
        rk.keep_time()


def test_deadlines_are_absolute_no_drift() -> None:
    clk = FakeClock()
    rk = RateKeeper(100.0, clock=clk, sleep=clk.sleep)
    rk.start()
    t0 = clk.t
    # varying work and wake-up jitter: the grid must not drift
    run_cycles(rk, clk, [0.001, 0.004, 0.0095, 0.0, 0.002] * 200, wake_jitter=0.0002)
    assert rk.cycles == 1000
    assert rk.misses == 0
    # after 1000 cycles we are sleeping until exactly t0 + 1000 periods
    assert clk.t == pytest.approx(t0 + 1000 * 0.01, abs=1e-9)


def test_overrun_skips_missed_periods_and_counts_them() -> None:
    clk = FakeClock()
    rk = RateKeeper(100.0, clock=clk, sleep=clk.sleep)
    rk.start()
    t0 = clk.t
    run_cycles(rk, clk, [0.001])  # on time; next period starts at t0+0.01
    rk.begin_cycle()
    clk.t += 0.035  # runs from t0+0.01 to t0+0.045: deadline t0+0.02 missed
    missed = rk.keep_time()
    assert missed
    assert rk.misses == 1
    # periods starting at t0+0.02, 0.03, 0.04 were skipped; next starts at t0+0.05
    assert rk.skipped_periods == 3
    assert clk.t == pytest.approx(t0 + 0.05, abs=1e-9)
    assert rk.cycle_start == pytest.approx(t0 + 0.05, abs=1e-9)
    run_cycles(rk, clk, [0.001] * 10)
    assert rk.misses == 1
    assert clk.t == pytest.approx(t0 + 0.15, abs=1e-9)


def test_statistics_reflect_lateness_and_compute() -> None:
    clk = FakeClock()
    rk = RateKeeper(50.0, clock=clk, sleep=clk.sleep)
    rk.start()
    # lateness 0.3 ms every cycle, compute 2 ms, one cycle with 5 ms compute
    work = [0.002] * 99 + [0.005]
    run_cycles(rk, clk, work, wake_jitter=0.0003)
    s = rk.stats()
    assert s.cycles == 100
    assert s.lateness_us_p50 == pytest.approx(300.0, abs=1e-3)
    assert s.lateness_us_max == pytest.approx(300.0, abs=1e-3)
    assert s.compute_us_p50 == pytest.approx(2000.0, abs=1e-3)
    assert s.compute_us_max == pytest.approx(5000.0, abs=1e-3)
    assert s.misses == 0
    d = s.as_dict()
    assert set(d) >= {"lateness_us_p99", "compute_us_p99", "misses", "skipped_periods"}


def test_window_is_bounded() -> None:
    clk = FakeClock()
    rk = RateKeeper(100.0, clock=clk, sleep=clk.sleep, window=10)
    rk.start()
    run_cycles(rk, clk, [0.008] * 10 + [0.001] * 10)
    assert rk.stats().compute_us_max == pytest.approx(1000.0, abs=1e-3)
    assert rk.cycles == 20


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_rejects_bad_rate(bad: float) -> None:
    with pytest.raises(ValueError):
        RateKeeper(bad)
