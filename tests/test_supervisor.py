"""Supervisor modes from plain inputs: every cause, its mode, its timing, and recovery."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from truckd.control.supervisor import (
    Decision,
    Mode,
    Supervisor,
    SupervisorConfig,
    SupervisorInputs,
)

P = 0.01  # control period, s


def healthy(t: float, **kw: object) -> SupervisorInputs:
    base = SupervisorInputs(
        t=t,
        link_up=True,
        link_age=0.002,
        encoder_age=0.004,
        range_age=0.02,
        range_value=1.0 + 1e-3 * math.sin(37 * t),  # noisy real sensor
        speed=1.0,
    )
    return dataclasses.replace(base, **kw)  # type: ignore[arg-type]


def run(
    sup: Supervisor, t0: float, t1: float, make: Callable[[float], SupervisorInputs]
) -> list[Decision]:
    out = []
    n = round((t1 - t0) / P)
    for k in range(n):
        out.append(sup.update(make(t0 + k * P)))
    return out


def active_supervisor(lead_lost_action: str = "stop", **cfg: object) -> tuple[Supervisor, float]:
    sup = Supervisor(SupervisorConfig(**cfg), lead_lost_action)  # type: ignore[arg-type]
    ds = run(sup, 0.0, 0.1, healthy)
    assert ds[-1].mode == Mode.ACTIVE
    return sup, 0.1


def test_init_until_link_and_sensors_fresh() -> None:
    sup = Supervisor()
    inf = math.inf
    assert sup.update(healthy(0.0, link_up=False)).mode == Mode.INIT
    assert sup.update(healthy(0.01, encoder_age=inf, range_age=inf)).mode == Mode.INIT
    assert sup.update(healthy(0.02, range_age=inf)).mode == Mode.INIT
    d = sup.update(healthy(0.03))
    assert d.mode == Mode.ACTIVE
    assert d.transition is not None and d.transition.old == Mode.INIT


@pytest.mark.parametrize(
    ("field", "cause"),
    [
        ("encoder_age", "encoder_stale"),
        ("speed_age", "speed_stale"),
        ("link_age", "link_stale"),
        ("range_age", "range_stale"),
    ],
)
def test_stale_data_stops_on_the_detection_cycle(field: str, cause: str) -> None:
    sup, t = active_supervisor()
    cfg = sup.config
    timeout = {
        "encoder_age": cfg.encoder_timeout_s,
        "speed_age": 2.0 * cfg.encoder_timeout_s,
        "link_age": cfg.link_timeout_s,
        "range_age": cfg.range_timeout_s,
    }[field]
    stopped_at = None
    # the data stops arriving at t: its age grows with time
    for k in range(100):
        tk = t + k * P
        d = sup.update(healthy(tk, **{field: k * P}))
        if d.mode != Mode.ACTIVE:
            stopped_at = k * P
            assert d.mode == Mode.SAFE_STOP
            assert cause in d.causes
            break
    assert stopped_at is not None
    # detected on the first cycle whose age exceeds the timeout (within one period)
    assert timeout < stopped_at <= timeout + P + 1e-9


def test_link_down_is_fault_and_recovers_after_recovery_time() -> None:
    sup, t = active_supervisor(recovery_s=0.3)
    d = sup.update(healthy(t, link_up=False))
    assert d.mode == Mode.FAULT and "link_down" in d.causes
    ds = run(sup, t + P, t + 0.5, lambda tk: healthy(tk, link_up=False, link_age=tk - t))
    assert all(x.mode == Mode.FAULT for x in ds)
    t2 = t + 0.5
    ds = run(sup, t2, t2 + 0.5, healthy)
    modes = [x.mode for x in ds]
    back = modes.index(Mode.ACTIVE)
    assert all(m == Mode.FAULT for m in modes[:back])
    assert back * P == pytest.approx(0.3, abs=P + 1e-9)


@pytest.mark.parametrize(("action", "mode"), [("stop", Mode.SAFE_STOP), ("cruise", Mode.DEGRADED)])
def test_lead_lost_by_config(action: str, mode: Mode) -> None:
    sup, t = active_supervisor(lead_lost_action=action)
    d = sup.update(healthy(t, lead_valid=False))
    assert d.mode == mode and "lead_lost" in d.causes


def test_range_sensor_fault_stops_even_when_lead_lost_means_cruise() -> None:
    # a faulty sensor is not "no target": no blind cruising
    sup, t = active_supervisor(lead_lost_action="cruise", recovery_s=0.1)
    d = sup.update(healthy(t, lead_valid=False, range_value=None, range_fault=True))
    assert d.mode == Mode.SAFE_STOP and d.causes == ("range_fault",)
    ds = run(sup, t + P, t + 0.3, healthy)
    assert ds[0].mode == Mode.SAFE_STOP and ds[-1].mode == Mode.ACTIVE
    assert Supervisor().update(healthy(0.0, range_fault=True)).mode == Mode.INIT


def test_solver_failures_degrade_then_stop_then_recover() -> None:
    sup, t = active_supervisor(solver_fail_limit=4, solver_degrade_after=2, recovery_s=0.1)
    modes = [sup.update(healthy(t + k * P, solver_ok=False)).mode for k in range(6)]
    assert modes == [Mode.ACTIVE] + [Mode.DEGRADED] * 2 + [Mode.SAFE_STOP] * 3
    ds = run(sup, t + 0.06, t + 0.3, healthy)
    assert ds[0].mode == Mode.SAFE_STOP
    assert ds[-1].mode == Mode.ACTIVE


def test_overruns_degrade_then_stop() -> None:
    sup, t = active_supervisor(overrun_limit=3, overrun_degrade_after=1)
    modes = [sup.update(healthy(t + k * P, loop_missed=True)).mode for k in range(4)]
    assert modes == [Mode.DEGRADED, Mode.DEGRADED, Mode.SAFE_STOP, Mode.SAFE_STOP]
    # one good cycle resets the consecutive count but the stop holds for recovery_s
    assert sup.update(healthy(t + 0.04)).mode == Mode.SAFE_STOP


def test_isolated_misses_and_failures_only_counted() -> None:
    sup, t = active_supervisor()
    for k in range(50):
        d = sup.update(healthy(t + k * P, loop_missed=k % 3 == 0, solver_ok=k % 4 != 1))
        assert d.mode == Mode.ACTIVE


def test_frozen_range_counts_driving_time_only_and_latches() -> None:
    sup, t = active_supervisor(range_frozen_s=0.3)
    ds = run(sup, t, t + 1.0, lambda tk: healthy(tk, range_value=1.234, speed=0.0))
    assert all(d.mode == Mode.ACTIVE for d in ds)
    ds = run(sup, t + 1.0, t + 2.0, lambda tk: healthy(tk, range_value=1.234, speed=1.0))
    first = next(k for k, d in enumerate(ds) if d.mode != Mode.ACTIVE)
    assert ds[first].mode == Mode.SAFE_STOP and "range_frozen" in ds[first].causes
    assert first * P == pytest.approx(0.3, abs=P + 1e-9)
    # stopped, same value: still frozen (no oscillation between stop and drive)
    ds = run(sup, t + 2.0, t + 3.0, lambda tk: healthy(tk, range_value=1.234, speed=0.0))
    assert all("range_frozen" in d.causes for d in ds)
    # the value moves again: cleared, and ACTIVE after the recovery time
    ds = run(sup, t + 3.0, t + 4.0, lambda tk: healthy(tk, speed=0.0))
    assert "range_frozen" not in ds[0].causes
    assert ds[-1].mode == Mode.ACTIVE


def test_transitions_are_logged_in_order() -> None:
    sup, t = active_supervisor(recovery_s=0.05)
    sup.update(healthy(t, link_up=False))
    run(sup, t + P, t + 0.2, healthy)
    seq = [(tr.old, tr.new) for tr in sup.transitions]
    assert seq == [(Mode.INIT, Mode.ACTIVE), (Mode.ACTIVE, Mode.FAULT), (Mode.FAULT, Mode.ACTIVE)]
    assert sup.transitions[1].as_dict()["causes"] == ["link_down"]


ages = st.one_of(st.floats(0, 1.0), st.just(math.inf), st.just(math.nan))


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.booleans(), ages, ages, ages, ages, st.booleans(), st.booleans(), st.booleans()
        ),
        min_size=1,
        max_size=40,
    )
)
def test_never_active_with_a_stale_or_missing_input(
    seq: list[tuple[bool, float, float, float, float, bool, bool, bool]],
) -> None:
    sup = Supervisor()
    cfg = sup.config
    for k, (up, la, ea, sa, ra, lead, solver, missed) in enumerate(seq):
        x = SupervisorInputs(
            t=k * P,
            link_up=up,
            link_age=la,
            encoder_age=ea,
            range_age=ra,
            range_value=float(k),
            speed=1.0,
            speed_age=sa,
            lead_valid=lead,
            solver_ok=solver,
            loop_missed=missed,
        )
        d = sup.update(x)
        fresh = (
            up
            and la <= cfg.link_timeout_s
            and ea <= cfg.encoder_timeout_s
            and sa <= 2.0 * cfg.encoder_timeout_s
            and ra <= cfg.range_timeout_s
        )
        if not fresh:
            assert d.mode in (Mode.INIT, Mode.SAFE_STOP, Mode.FAULT)
        if d.mode == Mode.ACTIVE:
            assert fresh and lead  # isolated solver failures and misses are only counted


def test_frozen_value_check_on_by_default_and_off_at_zero() -> None:
    """A stuck sensor whose firmware still stamps new sample times ran the truck into a
    braking lead (the check was off by default): one second of driving on one value stops
    it; 0 turns the check off (a noise-free sensor)."""
    sup, t = active_supervisor()
    ds = run(sup, t, t + 2.0, lambda tk: healthy(tk, range_value=1.234, speed=1.0))
    first = next(k for k, d in enumerate(ds) if d.mode != Mode.ACTIVE)
    assert ds[first].mode == Mode.SAFE_STOP and "range_frozen" in ds[first].causes
    assert first * P == pytest.approx(sup.config.range_frozen_s, abs=P + 1e-9)
    sup, t = active_supervisor(range_frozen_s=0.0)
    ds = run(sup, t, t + 5.0, lambda tk: healthy(tk, range_value=1.234, speed=1.0))
    assert all(d.mode == Mode.ACTIVE for d in ds)


def test_decide_is_update_and_an_unchanged_decision_is_given_again() -> None:
    """``decide`` of the inputs' fields decides as ``update`` of the record; while the mode
    and the causes stay, the same decision comes back (a transition or a new cause makes
    a new one)."""
    by_update, by_decide = Supervisor(), Supervisor()
    fields = [f.name for f in dataclasses.fields(SupervisorInputs)]
    inputs = [healthy(k * P) for k in range(60)]
    inputs += [healthy(0.6 + k * P, range_age=1.0) for k in range(5)]  # range_stale
    inputs += [healthy(0.65 + k * P) for k in range(80)]
    for x in inputs:
        a = by_update.update(x)
        b = by_decide.decide(*(getattr(x, f) for f in fields))
        assert a == b
    assert by_update.transitions == by_decide.transitions
    sup = Supervisor()
    decisions = run(sup, 0.0, 0.3, healthy)
    assert decisions[0].transition is not None and decisions[0].mode is Mode.ACTIVE
    assert decisions[1] is not decisions[0] and decisions[1].transition is None
    assert all(d is decisions[1] for d in decisions[2:])
    stale = sup.update(healthy(0.3, link_age=1.0))
    assert stale is not decisions[1] and stale.causes == ("link_stale",)


def test_a_commanded_motor_that_does_not_turn_stops_and_cools() -> None:
    """At least ``stall_command_v`` sent for ``stall_s`` while the truck stands: a stall
    (a stalled RS-540 draws some 80 A; a truck whose stiction its model does not know
    stood at 7.2 V for 15 s, mode DEGRADED). SAFE_STOP, held ``stall_cooldown_s``, then
    the usual recovery; a start that moves, and a command below the bound, do not trip."""
    sup, t = active_supervisor()
    cfg = sup.config
    # a start that breaks away within the time: nothing
    ds = run(sup, t, t + 1.0, lambda tk: healthy(tk, speed=0.0, command=4.0))
    ds += run(sup, t + 1.0, t + 2.0, lambda tk: healthy(tk, speed=0.5, command=4.0))
    assert all(d.mode == Mode.ACTIVE for d in ds)
    # below the bound, standing for long: nothing (a hold, a creep against a stop)
    t += 2.0
    ds = run(sup, t, t + 5.0, lambda tk: healthy(tk, speed=0.0, command=0.9 * cfg.stall_command_v))
    assert all(d.mode == Mode.ACTIVE for d in ds)
    # the stall
    t += 5.0
    ds = run(sup, t, t + 2.0, lambda tk: healthy(tk, speed=0.0, command=-4.0))
    first = next(k for k, d in enumerate(ds) if d.mode != Mode.ACTIVE)
    assert ds[first].mode == Mode.SAFE_STOP and "motor_stalled" in ds[first].causes
    assert first * P == pytest.approx(cfg.stall_s, abs=P + 1e-9)
    t_stall = t + first * P
    # the motor is off now: the cause holds for the cool-down, then the recovery time
    t += 2.0
    ds = run(sup, t, t + 6.0, lambda tk: healthy(tk, speed=0.0, command=0.0))
    back = next(k for k, d in enumerate(ds) if d.mode == Mode.ACTIVE)
    t_back = t + back * P
    want = t_stall + cfg.stall_cooldown_s + cfg.recovery_s
    assert t_back == pytest.approx(want, abs=2 * P + 1e-9)


def test_a_stall_needs_a_speed_to_judge() -> None:
    """Without encoder data nothing is known of the speed: the stale encoder is the
    cause, not a stall."""
    sup, t = active_supervisor()
    ds = run(sup, t, t + 3.0, lambda tk: healthy(tk, speed=0.0, command=5.0, encoder_age=1.0))
    assert all("motor_stalled" not in d.causes for d in ds)
    assert all("encoder_stale" in d.causes for d in ds)


def test_the_stall_check_is_off_at_zero() -> None:
    sup, t = active_supervisor(stall_command_v=0.0)
    ds = run(sup, t, t + 3.0, lambda tk: healthy(tk, speed=0.0, command=7.0))
    assert all(d.mode == Mode.ACTIVE for d in ds)


def test_a_loop_stall_does_not_end_a_stalls_cool_down() -> None:
    """``restart`` (a loop stall) resets the counters, not the stalled motor's cool-down:
    the truck drove into the same wall 1.2 s after the stall."""
    sup, t = active_supervisor()
    cfg = sup.config
    run(sup, t, t + cfg.stall_s + 0.05, lambda tk: healthy(tk, speed=0.0, command=5.0))
    t += cfg.stall_s + 0.05
    sup.restart(t + 0.5)
    ds = run(sup, t + 0.5, t + 3.0, lambda tk: healthy(tk, speed=0.0, command=0.0))
    assert all(d.mode != Mode.ACTIVE for d in ds)
    assert "motor_stalled" in ds[-1].causes
