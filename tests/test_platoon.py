"""Platooning, pure parts: plan messages, the lead forecast aligned in time, CACC/ACC."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from truckd.config.truck import load_config
from truckd.control.platoon import (
    ACC,
    CACC,
    PlatoonConfig,
    PlatoonMode,
    decode_plan,
    encode_plan,
    kinematic_plan,
    lead_forecast,
    make_plan,
    plan_of_array,
    plan_of_floats,
    plan_speed,
)

TICKS = load_config().ticks_per_rev


def test_plan_round_trip_and_accelerations() -> None:
    p = make_plan(10.0, 7, 0.01, [1.0, 1.02, 1.05], "truck2")
    assert p.a == pytest.approx((2.0, 3.0, 3.0))
    q = decode_plan(encode_plan(p))
    assert q == p
    d = json.loads(encode_plan(p))
    assert {"t", "seq", "dt", "v", "a"} <= set(d)


@pytest.mark.parametrize(
    "bad",
    [
        b"not json",
        b"[1, 2]",
        b'{"t": 1, "seq": 1, "dt": 0.01, "v": [1, 2], "a": [0]}',
        b'{"t": 1, "seq": 1, "dt": 0, "v": [1], "a": [0]}',
        b'{"t": 1, "seq": 1.5, "dt": 0.01, "v": [1], "a": [0]}',
        b'{"t": 1, "seq": 1, "dt": 0.01, "v": [NaN], "a": [0]}',
        b'{"t": 1, "seq": 1, "dt": 0.01, "v": [-1], "a": [0]}',
        b'{"t": 1, "seq": 1, "dt": 0.01, "v": [], "a": []}',
        b'{"seq": 1, "dt": 0.01, "v": [1], "a": [0]}',
    ],
)
def test_decode_refuses_bad_plans(bad: bytes) -> None:
    with pytest.raises(ValueError):
        decode_plan(bad)


def test_forecast_is_shifted_by_the_plan_age() -> None:
    # speeds 0, 0.1, 0.2, ... at t = 5.00, 5.01, ...: a plan 0.03 s old starts at 0.3
    p = make_plan(5.0, 1, 0.01, [0.1 * k for k in range(41)])
    f = lead_forecast(p, 5.03, 0.01, 5)
    assert f == pytest.approx([0.3, 0.4, 0.5, 0.6, 0.7])
    # between samples: linear
    assert plan_speed(p, 5.005) == pytest.approx(0.05)


@pytest.mark.parametrize("t", [4.0, 4.995, 5.0, 5.003, 5.2, 5.37, 5.4, 6.0])
def test_forecast_is_the_plan_speed_at_each_step(t: float) -> None:
    """lead_forecast repeats plan_speed's arithmetic inline: the same value, to the bit,
    before, within and after a plan (held and braking ends)."""
    plans = (
        make_plan(5.0, 1, 0.01, [0.1 * k for k in range(41)]),
        kinematic_plan(5.0, 1, 0.02, 1.0, -2.0, 20),
    )
    for p in plans:
        for dt in (0.01, 0.007):
            f = lead_forecast(p, t, dt, 40)
            assert f == [plan_speed(p, t + k * dt) for k in range(40)]


def test_forecast_past_the_plan_end_holds_or_keeps_braking() -> None:
    cruise = make_plan(0.0, 1, 0.1, [1.0, 1.1, 1.2])  # accelerating: held, not extrapolated
    assert plan_speed(cruise, 5.0) == pytest.approx(1.2)
    brake = kinematic_plan(0.0, 1, 0.1, 1.0, -2.0, 2)  # 1.0, 0.8, 0.6 then still braking
    assert plan_speed(brake, 0.3) == pytest.approx(0.4)
    assert plan_speed(brake, 10.0) == 0.0


def _mode(**kw: float) -> PlatoonMode:
    return PlatoonMode(PlatoonConfig(**kw), 0.01, 10, initial=CACC)  # type: ignore[arg-type]


def test_cacc_while_fresh_acc_when_stale_and_back_after_the_return_time() -> None:
    cfg = PlatoonConfig()
    m = PlatoonMode(cfg, 0.01, 10, initial=CACC)
    t = 0.0
    plan = kinematic_plan(0.0, 0, 0.01, 1.0, 0.0, 40)
    while t < 1.0:  # fresh plans every cycle
        plan = kinematic_plan(t, round(t * 100), 0.01, 1.0, 0.0, 40)
        d = m.update(t, plan, 1.0, 0.4 + cfg.cacc_headway, 0.4)
        assert d.mode == CACC and d.forecast is not None and len(d.forecast) == 10
        t += 0.01
    last = plan
    switched = None
    while t < 3.0:  # plans stop: ACC once the last one is older than the hold time
        d = m.update(t, last, 1.0, 0.4 + 1.0 * m.headway, 0.4)
        if d.mode == ACC and switched is None:
            switched = t
        if switched is not None:
            assert d.mode == ACC and d.forecast is None
        t += 0.01
    assert switched is not None
    assert switched - last.t == pytest.approx(cfg.plan_hold_s, abs=0.011)
    assert cfg.plan_hold_s > cfg.plan_timeout_s
    # the headway ramps up at the configured rate, never jumps
    assert m.headway == pytest.approx(
        min(cfg.cacc_headway + cfg.headway_rate * (t - switched), cfg.acc_headway), abs=0.01
    )
    back = None
    t_fresh = t
    while t < 4.0:
        plan = kinematic_plan(t, round(t * 100), 0.01, 1.0, 0.0, 40)
        d = m.update(t, plan, 1.0, 1.5, 0.4)
        if d.mode == CACC and back is None:
            back = t
        t += 0.01
    assert back is not None
    assert back - t_fresh == pytest.approx(cfg.cacc_return_s, abs=0.011)
    assert m.switches == 2


def test_a_burst_of_lost_plans_is_ridden_out_on_the_last_plan_shifted_in_time() -> None:
    """Plans stop for 0.5 s (a burst): the follower stays in CACC on the last plan, its
    forecast the plan's speeds at the follower's own times (so the plan's braking goes on
    in the forecast as time passes), past the plan's end the lead speed the range sensor
    measures when lower; plans again: fresh at once, no switch.  Without the hold
    (``plan_hold_s`` at most the timeout) the same burst switches to ACC."""
    cfg = PlatoonConfig()
    m = PlatoonMode(cfg, 0.01, 30, initial=CACC)
    t = 0.0
    for _ in range(100):
        d = m.update(t, kinematic_plan(t, round(t * 100), 0.01, 1.0, 0.0, 55), 1.0, 0.7, 0.4)
        t += 0.01
    # the last plan: brakes at 1 m/s^2 to 0.7 m/s, then holds it (0.55 s in all)
    last = make_plan(t, round(t * 100), 0.01, [max(1.0 - 0.01 * k, 0.7) for k in range(56)])
    t_last = t
    for k in range(50):  # the burst: 0.5 s without a plan; the range sensor: 0.6 m/s
        t = t_last + k * 0.01
        d = m.update(t, last, 1.0, 0.7, 0.4, v_lead=0.6)
        assert d.mode == CACC and d.forecast is not None
        # the plan aged: its speed at this truck's time t, not its first speed
        assert d.forecast[0] == pytest.approx(max(1.0 - (t - t_last), 0.7), abs=1e-9)
        assert d.plan_age_s == pytest.approx(t - t_last)
    # 0.49 s old: past the plan's end (0.55 s) the range sensor's lower 0.6 m/s
    assert d.forecast[5] == pytest.approx(0.7) and d.forecast[7] == pytest.approx(0.6)
    assert m.switches == 0
    t += 0.01
    d = m.update(t, kinematic_plan(t, 999, 0.01, 0.6, 0.0, 55), 0.6, 0.58, 0.4)
    assert d.mode == CACC and m.switches == 0
    # the same burst without the hold: ACC
    m0 = PlatoonMode(replace(cfg, plan_hold_s=0.0), 0.01, 30, initial=CACC)
    m0.update(t_last - 0.01, last, 1.0, 0.7, 0.4)
    modes = [m0.update(t_last + k * 0.01, last, 1.0, 0.7, 0.4).mode for k in range(50)]
    assert modes[5] == CACC and modes[-1] == ACC
    # a plan never seen fresh (a clock that disagrees: always 0.5 s old) is not held
    m1 = PlatoonMode(cfg, 0.01, 30, initial=CACC)
    assert m1.update(10.0, kinematic_plan(9.5, 1, 0.01, 1.0, 0.0, 55), 1.0, 0.7, 0.4).mode == ACC
    # and once a held plan is older than plan_hold_s: ACC, the forecast dropped
    d = m.update(t + cfg.plan_hold_s + 0.02, last, 1.0, 0.7, 0.4)
    assert d.mode == ACC and d.forecast is None


def test_headway_ramp_starts_from_the_gap_actually_driven() -> None:
    m = _mode(cacc_headway=0.5, acc_headway=1.1, headway_rate=0.1)
    plan = kinematic_plan(0.0, 0, 0.01, 1.0, 0.0, 40)
    m.update(0.0, plan, 1.0, 0.4 + 0.5, 0.4)
    # stale; the truck happens to drive 0.8 s behind: the ramp starts there
    d = m.update(1.0, plan, 1.0, 0.4 + 0.8, 0.4)
    assert d.mode == ACC
    assert d.headway == pytest.approx(0.8 + 0.1 * 0.01)


def test_plans_from_the_future_are_refused() -> None:
    m = _mode(max_clock_skew_s=0.05)
    future = kinematic_plan(1.0, 0, 0.01, 1.0, 0.0, 40)
    assert not m.fresh(future, 0.9)
    assert m.fresh(future, 0.97)
    assert not m.fresh(None, 1.0)


def test_config_rejects_acc_headway_below_cacc() -> None:
    assert PlatoonConfig(cacc_headway=0.5, acc_headway=0.4).validate() is not None
    assert PlatoonConfig().validate() is None
    assert math.isfinite(PlatoonConfig().acc_headway)


def test_controller_headway_hook_sets_the_spacing_it_drives() -> None:
    """At the gap of a 1.1 s headway, a controller told to drive 1.1 s holds its speed;
    the same controller on its configured 0.5 s closes the gap (plans to go faster)."""
    from truckd.config.truck import load_config
    from truckd.control.controller import Controller
    from truckd.control.estimator import Estimate
    from truckd.control.qp import ControlModel

    cfg = load_config()
    control = replace(cfg.control, time_headway=0.5).in_simulated_time()
    v = 1.2
    gap = control.d_0 + 1.1 * v
    est = Estimate(v, True, gap, v, True, "tracking", 0.01, 0, 0, 10, 10)
    ends = {}
    for h in (1.1, None):
        ctrl = Controller(ControlModel(cfg.vehicle), control, TICKS)
        ctrl.u_prev = cfg.vehicle.K_v * cfg.vehicle.omega(v)
        out = ctrl.control(est, None, h)
        assert out.fallback_reason is None
        assert out.gap_ref == pytest.approx(control.d_0 + (h or 0.5) * v)
        z = ctrl.mpc.last_solution
        assert z is not None
        ends[h] = float(max(ctrl.mpc.qp.plan(z)[1]))
    assert ends[1.1] == pytest.approx(v, abs=0.03)
    assert ends[None] > v + 0.1


def test_a_plan_at_odds_with_the_range_sensor_is_not_followed() -> None:
    """The plan says 1.5 m/s, the range sensor's filter says the lead is at 0.5: ACC (no
    forecast), counted; within the tolerance plus three standard deviations of the
    filter: CACC.  An uncertain filter (a target just found) is not overruled."""
    cfg = PlatoonConfig()
    m = PlatoonMode(cfg, 0.01, 10, initial=CACC)
    plan = kinematic_plan(0.0, 0, 0.01, 1.5, 0.0, 40)
    d = m.update(0.0, plan, 1.5, 1.0, 0.4, 1.5 - cfg.plan_speed_tolerance + 0.05, 0.01)
    assert d.mode == CACC and d.forecast is not None
    d = m.update(0.01, plan, 1.5, 1.0, 0.4, 0.5, 0.01)
    assert d.mode == ACC and d.forecast is None and m.disagreements == 1
    m2 = PlatoonMode(cfg, 0.01, 10, initial=CACC)
    d = m2.update(0.0, plan, 1.5, 1.0, 0.4, 0.5, 1.0)  # 1 m/s uncertain: no verdict
    assert d.mode == CACC and m2.disagreements == 0
    m3 = PlatoonMode(cfg, 0.01, 10, initial=CACC)
    d = m3.update(0.0, plan, 1.5, 1.0, 0.4, math.nan, math.nan)  # no lead in range
    assert d.mode == CACC


@pytest.mark.parametrize(
    "speeds",
    [
        [1.3, 1.31, 1.33, 1.36, 1.4],
        [0.2, 0.05, -1e-9, -0.0, 0.1],  # clipped: a negative speed
        [1.0, math.nan, 1.2, -0.5],  # a NaN kept, the negative clipped
        [1.0, math.nan, 1.2],  # a NaN alone: nothing clipped
        [0.7],
    ],
)
def test_plan_of_array_is_plan_of_floats_to_the_bit(speeds: list[float]) -> None:
    """The plan from the MPC's speed array: the same speeds, accelerations and clipping as
    from Python floats, bit for bit (NaN and -0.0 included), the array untouched."""
    arr = np.array(speeds)
    a, b = plan_of_array(2.5, 7, 0.01, arr, "t1"), plan_of_floats(2.5, 7, 0.01, list(speeds), "t1")
    assert repr(a) == repr(b)
    assert [math.copysign(1.0, x) for x in a.v] == [math.copysign(1.0, x) for x in b.v]
    assert all(type(x) is float for x in (*a.v, *a.a))
    assert np.array_equal(arr, np.array(speeds), equal_nan=True)
    with pytest.raises(ValueError):
        plan_of_array(0.0, 0, 0.01, np.zeros(0))
