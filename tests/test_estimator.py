"""The estimator: wrapping counters, speed from quantised ticks of both wheels, the lead
filter's outlier rejection, cut-in re-initialisation and lead-lost detection."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from truckd.control.config import EstimatorConfig
from truckd.control.estimator import (
    EncoderSample,
    Estimator,
    RangeSample,
    wrap_delta,
    wrap_dt,
)

R_W = 0.0425
TICKS = 512
TICK_LEN = 2 * math.pi * R_W / TICKS
MOD = 65536
DT = 0.01


@given(start=st.integers(0, MOD - 1), delta=st.integers(-MOD // 2, MOD // 2 - 1))
def test_wrap_delta_inverts_modular_addition(start: int, delta: int) -> None:
    assert wrap_delta((start + delta) % MOD, start, MOD) == delta


def test_wrap_dt_across_the_clock_wrap() -> None:
    assert wrap_dt(0.0049, 6.5486, 6.5536) == pytest.approx(0.0099)


def drive(
    est: Estimator,
    v: float,
    n: int,
    x0: float = 0.0,
    t0: float = 0.0,
    tick0: int = 0,
    right_ok: bool = True,
    right_garbage: bool = False,
) -> tuple[float, float]:
    """Feed n encoder samples of a truck at constant speed v; returns (x, t) at the end."""
    x, t = x0, t0
    for _ in range(n):
        t += DT
        x += v * DT
        ticks = (tick0 + math.floor(x / TICK_LEN)) % MOD
        right = 12345 if right_garbage else ticks
        est.update_encoders(
            t, EncoderSample(ticks, right, t % 6.5536, left_ok=True, right_ok=right_ok)
        )
    return x, t


@pytest.mark.parametrize("v", [0.3, 1.0, 2.4])
def test_speed_from_ticks_across_the_counter_wrap(v: float) -> None:
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    # Start just below the wrap so the counters wrap during the run.
    x, t = drive(est, v, 200, tick0=MOD - 200)
    errors = []
    for _ in range(100):
        x, t = drive(est, v, 1, x0=x, t0=t, tick0=MOD - 200)
        speed, fresh = est.speed(t)
        assert fresh
        errors.append(speed - v)
    # One tick per 10 ms sample is 0.052 m/s of quantisation: unbiased, and every
    # estimate within that.
    assert abs(sum(errors) / len(errors)) < 0.005
    assert max(abs(e) for e in errors) < 0.052


def test_speed_uses_the_healthy_wheel_when_one_encoder_fails() -> None:
    """The failed wheel's garbage counts are ignored: over 3 s after settling the speed is
    unbiased and within one sample's quantisation (0.052 m/s) at every sample (a single
    sample's error is up to 0.02-0.03 m/s, so one sample checked to 0.01 passed by luck)."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x, t = drive(est, 1.0, 200, right_ok=False, right_garbage=True)
    errors = []
    for _ in range(300):
        x, t = drive(est, 1.0, 1, x0=x, t0=t, right_ok=False, right_garbage=True)
        errors.append(est.speed(t)[0] - 1.0)
    assert abs(sum(errors) / len(errors)) < 0.005
    assert sum(abs(e) for e in errors) / len(errors) < 0.015
    assert max(abs(e) for e in errors) < TICK_LEN / DT


def test_speed_goes_stale_without_encoder_samples() -> None:
    cfg = EstimatorConfig()
    est = Estimator(cfg, R_W, TICKS)
    _, t = drive(est, 1.0, 50)
    assert est.speed(t)[1]
    assert not est.speed(t + cfg.encoder_timeout_s + 0.001)[1]


def follow_range(
    est: Estimator, gap0: float, v_lead: float, v_own: float, n: int, t0: float = 0.0
) -> float:
    """Range readings every 20 ms of a lead at v_lead, own truck at v_own; returns t."""
    t = t0
    for k in range(n):
        t = t0 + (k + 1) * 0.02
        gap = gap0 + (v_lead - v_own) * (t - t0)
        est.update_range(t, RangeSample(gap, t), v_own)
    return t


def test_lead_speed_converges_and_a_spike_is_rejected() -> None:
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    t = follow_range(est, 1.5, v_lead=1.0, v_own=1.2, n=100)
    e = est.estimate(t)
    assert e.lead_valid
    assert e.v_lead == pytest.approx(1.0, abs=0.02)
    gap_true = 1.5 - 0.2 * (t - 0.0)
    assert e.gap == pytest.approx(gap_true, abs=0.01)
    # One wild reading (a reflection) is rejected; the estimate barely moves.
    t += 0.02
    est.update_range(t, RangeSample(0.3, t), 1.2)
    e2 = est.estimate(t)
    assert e2.outliers == 1
    assert e2.gap == pytest.approx(gap_true - 0.2 * 0.02, abs=0.01)


def test_cut_in_restarts_the_filter_after_consistent_outliers() -> None:
    cfg = EstimatorConfig()
    est = Estimator(cfg, R_W, TICKS)
    t = follow_range(est, 1.2, v_lead=1.0, v_own=1.0, n=100)
    for k in range(cfg.reinit_count):
        t += 0.02
        est.update_range(t, RangeSample(0.6, t), 1.0)
        e = est.estimate(t)
        if k < cfg.reinit_count - 1:
            assert e.gap == pytest.approx(1.2, abs=0.02)  # still the old target
    assert e.reinits == 1
    assert e.gap == pytest.approx(0.6, abs=0.02)


def test_lead_lost_after_timeout_and_no_target_status() -> None:
    cfg = EstimatorConfig()
    est = Estimator(cfg, R_W, TICKS)
    t = follow_range(est, 1.0, 1.0, 1.0, 20)
    assert est.estimate(t).lead_valid
    # Out of range: no target, lead held for the timeout, then lost.
    t += 0.02
    est.update_range(t, RangeSample(cfg.range_max + 1.0, t), 1.0)
    assert est.estimate(t).lead_valid
    lost = est.estimate(t + cfg.lead_timeout_s + 0.001)
    assert not lost.lead_valid and lost.lead_status == "no_target"


def test_silence_is_a_timeout_and_a_new_reading_restarts() -> None:
    cfg = EstimatorConfig()
    est = Estimator(cfg, R_W, TICKS)
    t = follow_range(est, 1.0, 1.0, 1.0, 20)
    t_late = t + cfg.lead_timeout_s + 0.05
    e = est.estimate(t_late)
    assert not e.lead_valid and e.lead_status == "timeout"
    est.update_range(t_late, RangeSample(2.0, t_late), 1.0)
    e = est.estimate(t_late)
    assert e.lead_valid and e.gap == pytest.approx(2.0)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0, None])
def test_invalid_readings_are_no_target(bad: float | None) -> None:
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    est.update_range(0.0, RangeSample(bad, 0.0), 0.0)
    e = est.estimate(0.0)
    assert not e.lead_valid and e.lead_status == "no_target"


def test_rejects_a_bad_tick_resolution() -> None:
    with pytest.raises(ValueError, match="ticks_per_rev"):
        Estimator(EstimatorConfig(), R_W, 0)


def test_a_sample_without_a_finite_time_is_ignored_not_poisoning_the_filters() -> None:
    """A NaN or infinite time stamp (caller or firmware) is no sample: the speed and the
    lead filter go on from the samples around it, finite."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x, t = drive(est, 1.0, 50)
    est.update_range(t, RangeSample(1.0, t), 1.0)
    for bad in (math.nan, math.inf):
        est.update_encoders(t, EncoderSample(5, 5, bad))
        est.update_encoders(bad, EncoderSample(5, 5, t))
        est.update_range(t, RangeSample(1.0, bad), 1.0)
        est.update_range(bad, RangeSample(1.0, t), 1.0)
        est.update_range(t, RangeSample(1.0, t), bad)
    x, t = drive(est, 1.0, 10, x0=x, t0=t)
    est.update_range(t, RangeSample(1.0 - 0.1, t), 1.0)
    e = est.estimate(t)
    assert e.speed_valid and e.v == pytest.approx(1.0, abs=0.05)
    assert e.lead_valid and math.isfinite(e.gap) and math.isfinite(e.v_lead)


def _samples(
    v: float, n: int, t0: float, clock0: float, tick0: int, x0: float = 0.0
) -> list[tuple[float, EncoderSample]]:
    """n encoder samples of a truck at speed v (m/s): (caller time, sample)."""
    out = []
    for k in range(1, n + 1):
        x = x0 + v * k * DT
        ticks = (tick0 + math.floor(x / TICK_LEN)) % MOD
        out.append((t0 + k * DT, EncoderSample(ticks, ticks, (clock0 + k * DT) % 6.5536)))
    return out


@pytest.mark.parametrize("clock_before", [1.0, 2.0, 4.0, 5.5, 6.5])
def test_a_microcontroller_reset_restarts_the_speed_without_a_spike(clock_before: float) -> None:
    """After 0.2 s of silence the firmware's sample clock and counters start again from 0
    (a watchdog reset), wherever the old clock stood: behind it by more than half its wrap,
    or ahead of it by more than the caller's clock says passed.  The filter restarts from
    the new samples: valid again within three of them, never a speed the truck did not
    have (before: the samples were refused until the clock caught up, or gave +30 m/s)."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    n_before = round(clock_before / DT)
    for t, s in _samples(1.0, n_before, 0.0, 0.0, 1000):
        est.update_encoders(t, s)
    t_reset = n_before * DT + 0.2
    speeds = []
    for t, s in _samples(0.5, 50, t_reset, 0.0, 0):
        est.update_encoders(t, s)
        v, ok = est.speed(t)
        speeds.append((v, ok))
    assert all(ok for _, ok in speeds[3:])
    assert all(abs(v - 0.5) < 0.1 for v, ok in speeds[10:])
    assert all(-0.1 < v < 1.1 for v, ok in speeds if ok)
    assert est.estimate(t_reset + 0.5).speed_restarts == 1


@pytest.mark.parametrize("jump", [20000, -20000, 32767])
def test_a_counter_jump_is_a_restart_not_a_speed(jump: int) -> None:
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x, t = drive(est, 1.0, 100)
    x, t = drive(est, 1.0, 30, x0=x, t0=t, tick0=jump)  # every count shifted from here on
    v, ok = est.speed(t)
    assert ok and v == pytest.approx(1.0, abs=0.1)
    e = est.estimate(t)
    assert e.speed_restarts == 1


@pytest.mark.parametrize("held", [1, 2])
def test_a_count_read_before_it_moved_is_a_glitch_not_a_restart(held: int) -> None:
    """A sample whose count is the one before (read before the counter moved, or a late
    snapshot), then the counts catch up: one such sample is dropped, the speed stays valid
    and right, no restart (before: a restart, a cycle without speed, then a valid 1.6 m/s
    from the difference over the catch-up).  Two in a row are a discontinuity: the filter
    restarts, and no speed it calls valid is off (a first difference from the stale count
    would be 2.4 m/s: it waits for the next to confirm it)."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    v_true = 0.8
    x, t = drive(est, v_true, 100)
    stale = math.floor(x / TICK_LEN) % MOD
    for _ in range(held):
        t += DT
        x += v_true * DT
        est.update_encoders(t, EncoderSample(stale, stale, t % 6.5536))
    speeds = []
    for _ in range(10):
        x, t = drive(est, v_true, 1, x0=x, t0=t)
        speeds.append(est.speed(t))
    e = est.estimate(t)
    if held == 1:
        assert all(ok and abs(v - v_true) < 0.05 for v, ok in speeds), speeds
        assert (e.speed_restarts, e.speed_glitches) == (0, 1)
    else:
        assert e.speed_restarts >= 1 and e.speed_glitches == 0
        assert all(abs(v - v_true) < 0.1 for v, ok in speeds if ok), speeds
        assert all(ok for _, ok in speeds[6:]), speeds


def test_one_sample_out_of_order_is_dropped_without_a_restart() -> None:
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x, t = drive(est, 1.0, 100)
    old_ticks = math.floor((x - 0.05) / TICK_LEN) % MOD
    est.update_encoders(t, EncoderSample(old_ticks, old_ticks, (t - 0.05) % 6.5536))
    x, t = drive(est, 1.0, 5, x0=x, t0=t)
    v, ok = est.speed(t)
    assert ok and v == pytest.approx(1.0, abs=0.05)
    assert est.estimate(t).speed_restarts == 0


def test_wheels_failing_in_turn_leave_no_speed_and_its_age_grows() -> None:
    """The left encoder healthy in one sample, the right in the next: no wheel is healthy
    in two samples running, so no difference: the speed goes stale (the supervisor stops
    on its age) instead of being held."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x, t = drive(est, 1.0, 50)
    t_good = t + DT  # the first: the left wheel was healthy in the sample before as well
    for k in range(20):
        t += DT
        x += DT
        ticks = math.floor(x / TICK_LEN) % MOD
        flap = EncoderSample(ticks, ticks, t, left_ok=k % 2 == 0, right_ok=k % 2 == 1)
        est.update_encoders(t, flap)
    e = est.estimate(t)
    assert not e.speed_valid
    assert e.speed_age == pytest.approx(t - t_good)


def test_a_valid_reading_closer_than_the_minimum_range_is_a_target_at_it() -> None:
    """Not "no target" (which would let the truck cruise into what is right ahead)."""
    cfg = EstimatorConfig()
    est = Estimator(cfg, R_W, TICKS)
    est.update_range(0.0, RangeSample(0.0, 0.0), 0.0)
    e = est.estimate(0.0)
    assert e.lead_valid and e.gap == pytest.approx(cfg.range_min)


def test_a_reset_that_looks_like_an_ordinary_step_is_still_a_restart() -> None:
    """The old clock just below its wrap (the new one looks 0.1 s ahead, as a stalled
    link's would) and the old count 2000 ticks: under the speed bound the reset read as
    -19 m/s, valid.  The step lies far from the filter's speed: a restart."""
    est = Estimator(EstimatorConfig(), R_W, TICKS)
    x0 = 2000 * TICK_LEN - 300 * DT
    clock0 = 6.45 - 300 * DT
    for k in range(1, 301):
        ticks = math.floor((x0 + k * DT) / TICK_LEN) % MOD
        est.update_encoders(k * DT, EncoderSample(ticks, ticks, (clock0 + k * DT) % 6.5536))
    t_reset = 300 * DT + 0.2
    for k in range(1, 11):
        ticks = math.floor(0.5 * k * DT / TICK_LEN)
        t = t_reset + k * DT
        est.update_encoders(t, EncoderSample(ticks, ticks, k * DT))
        v, ok = est.speed(t)
        assert not ok or abs(v - 0.5) < 0.1, (k, v)
    assert est.estimate(t).speed_restarts == 1
