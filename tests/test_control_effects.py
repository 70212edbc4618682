"""The controller uses every effect of its model: closed loop per effect on a truck unlike
the shipped one, the extended model against the seed model on the same plant and seed;
and the pieces (the delay predictor, the battery sag map, the dead-zone law, the current
limit's record, the Stribeck feedforward, the winding's thermal model, the table) on known
inputs."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest

from truckd.config.truck import load_config
from truckd.control.controller import SATURATED_V, Controller
from truckd.control.effect_use import (
    EFFECT_USES,
    RISE_MAX,
    DeadZoneLaw,
    Winding,
    current_window,
    feedforward_torque,
    sag_command,
    sag_limit,
    startup_line,
    unused_effects,
)
from truckd.control.estimator import Estimate
from truckd.control.feedforward import (
    breakaway_feedforward,
    dead_zone_command,
    moving_feedforward,
    torque_to_voltage,
)
from truckd.control.qp import ControlModel
from truckd.model.effects import (
    COPPER_TEMPCO,
    EFFECT_NAMES,
    Effects,
    current_limited,
    driver_output,
)
from truckd.model.params import VehicleParams
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.plant import Plant, PlantConfig
from truckd.sim.scenarios import make_scenario

TICKS = load_config().ticks_per_rev

# -- closed loop ---------------------------------------------------------------------------


def _truck() -> VehicleParams:
    """Heavier, with more friction and a weaker motor than the shipped truck."""
    p = load_config().vehicle
    return p.replace(
        J_S=p.J_S * 1.6,
        K_coulomb=p.K_coulomb * 1.3,
        K_stiction=p.K_stiction * 1.3,
        R_m=p.R_m * 1.2,
        m=p.m * 1.4,
    )


CASES: dict[str, tuple[Effects, str, float]] = {
    # effect: (the plant's effects, scenario, duration in s)
    "viscous_friction": (Effects(viscous_friction=4e-5), "follow", 10.0),
    "aero_drag": (Effects(aero_drag=2.0), "follow", 10.0),
    "load_force": (Effects(load_force=4.0), "follow", 10.0),
    "load_force_amplitude": (
        Effects(load_force_amplitude=3.0, load_force_wavelength=3.0),
        "follow",
        14.0,
    ),
    "hill_force": (Effects(hill_force=4.0, hill_start=6.0, hill_length=4.0), "follow", 14.0),
    "input_delay": (Effects(input_delay=0.08), "lead-brake", 15.0),
    "dead_zone": (Effects(dead_zone=1.0), "stop-and-go", 18.0),
    "dead_zone_offset": (Effects(dead_zone_offset=0.8), "stop-and-go", 18.0),
    "voltage_saturation": (Effects(voltage_saturation=4.0), "lead-brake", 15.0),
    "battery_sag": (Effects(battery_sag=0.25), "follow", 10.0),
    "sensor_lag": (Effects(sensor_lag=0.1), "follow", 10.0),
    # Stop-and-go's starts at 12 A (a seventh of the stall current): the truck accelerates
    # at the limit; cutting the command at the speed estimated now made it 24 % worse.
    "current_limit": (Effects(current_limit=12.0), "stop-and-go", 18.0),
    "stribeck": (Effects(stribeck=0.01, stribeck_speed=0.1), "stop-and-go", 18.0),
    "resistance_drift": (
        Effects(resistance_drift=10.0, winding_time_constant=10.0),
        "follow",
        10.0,
    ),
}

CAPPED = {
    "current_limit": "a current-limited motor cannot accelerate harder: stop-and-go's starts "
    "lag the lead whatever the plan (seed and extended both command beyond the limit)",
}
"""Effects whose cost physics keeps (docs/controller.md, known gaps): the extended model is
held to never being worse than the seed's, not to recovering half."""

UNUSED: dict[str, tuple[Effects, str, float]] = {
    # 3 rad at the motor: 6 degrees at the wheel, the largest the scenarios measured.
    "backlash": (Effects(backlash=3.0), "lead-brake", 15.0),
}
"""Effects the diagnosis names that the controller does not use (named at start-up), with
the case showing that they cost under 2 mm of RMS gap error (nothing to recover)."""


def _run(plant_eff: Effects, model_eff: Effects, scenario: str, duration: float) -> Any:
    tc = load_config()
    p = _truck()
    setup = SimSetup(
        p,
        dataclasses.replace(tc.plant, effects=plant_eff),
        tc.control,
        ControlModel(p, model_eff),
        tc.link.encoder_ticks_per_rev,
        supervisor=tc.runtime.supervisor,
        stop_ramp_v_per_s=tc.runtime.stop_ramp_v_per_s,
    )
    m, _ = run_scenario(make_scenario(scenario, p, tc.control), setup, duration)
    return m


_CLEAN: dict[tuple[str, float], Any] = {}


def _clean(scenario: str, duration: float) -> Any:
    key = (scenario, duration)
    if key not in _CLEAN:
        _CLEAN[key] = _run(Effects(), Effects(), scenario, duration)
    return _CLEAN[key]


def test_every_effect_has_a_use_or_is_named_at_start_up() -> None:
    """Each effect the table covers has a closed-loop case here; any other effect (one the
    model gains later) is named by the start-up line, never silently ignored."""
    assert set(CASES) == set(EFFECT_USES)
    assert set(EFFECT_NAMES) <= set(CASES) | set(UNUSED)
    for name in (*EFFECT_NAMES, "load_force_amplitude", "hill_force"):
        eff = dataclasses.replace(Effects(), **{name: 0.5})
        line = startup_line(eff)
        assert (name in EFFECT_USES) == (line is None), (name, line)
        assert line is None or name in line


@pytest.mark.parametrize("name", list(CASES))
def test_extended_model_recovers_what_the_effect_costs(name: str) -> None:
    """Where the effect costs more than 2 mm of RMS gap error, the model that knows it
    recovers at least half; nowhere is it worse than the seed by more than 5 %."""
    eff, scenario, duration = CASES[name]
    clean = _clean(scenario, duration)["gap_error_rms_m"]
    seed = _run(eff, Effects(), scenario, duration)
    ext = _run(eff, eff, scenario, duration)
    assert not ext["collision"]
    s, e = seed["gap_error_rms_m"], ext["gap_error_rms_m"]
    assert e <= 1.05 * s + 2e-4, (name, clean, s, e)
    if s - clean > 0.002 and name not in CAPPED:
        assert (s - e) / (s - clean) >= 0.5, (name, clean, s, e)


def test_rolling_road_in_lead_brake_helps_the_seed_only_where_its_slopes_fall() -> None:
    """A rolling road in lead-brake: with its downhill where the truck stops (phase 0) the
    seed model ends *better* than the clean truck (the slope pushes the creeping truck
    nearer the standstill gap before the hold); the same road half a wavelength on makes
    the seed worse.  The extended model drives as the clean truck at both (within 5 %:
    the benchmark's ``helped`` rows) and recovers the cost where there is one."""
    clean = _clean("lead-brake", 15.0)["gap_error_rms_m"]
    for phase, helped in ((0.0, True), (math.pi, False)):
        eff = Effects(load_force_amplitude=3.0, load_force_wavelength=3.0, load_force_phase=phase)
        seed = _run(eff, Effects(), "lead-brake", 15.0)
        ext = _run(eff, eff, "lead-brake", 15.0)
        s, e = seed["gap_error_rms_m"], ext["gap_error_rms_m"]
        assert not ext["collision"]
        assert (s < clean - 0.002) == helped, (phase, clean, s, e)
        assert e <= 1.05 * clean + 2e-4, (phase, clean, s, e)
        if not helped:
            assert (s - e) / (s - clean) >= 0.5, (phase, clean, s, e)


@pytest.mark.parametrize("name", list(UNUSED))
def test_an_unused_effect_costs_too_little_to_recover(name: str) -> None:
    """The effects without a use cost under 2 mm of RMS gap error at their larger value
    (backlash: the rotor crosses the gap within about a cycle at a torque reversal)."""
    eff, scenario, duration = UNUSED[name]
    clean = _clean(scenario, duration)["gap_error_rms_m"]
    seed = _run(eff, Effects(), scenario, duration)
    assert not seed["collision"]
    assert seed["gap_error_rms_m"] - clean < 0.002, (name, clean, seed["gap_error_rms_m"])
    assert seed["gap_error_rms_m"] > clean  # the effect is there: it costs something
    line = startup_line(eff)
    assert line is not None and name in line


# -- the pieces ----------------------------------------------------------------------------


@pytest.mark.parametrize("current", [-20.0, 0.0, 5.0, 20.0])
@pytest.mark.parametrize("wanted", [-4.0, -0.5, 0.8, 3.0, 5.5])
def test_sag_command_makes_the_driver_apply_the_wanted_voltage(
    wanted: float, current: float
) -> None:
    r_b, v_batt = 0.3, 7.2
    c = sag_command(wanted, r_b, v_batt, current)
    applied = c - r_b * (c / v_batt) ** 2 * current  # the plant's driver (sim.plant)
    a = r_b * current / v_batt**2
    if 4.0 * a * wanted < 1.0:
        assert applied == pytest.approx(wanted, abs=1e-9)
        assert abs(c) >= abs(wanted) or current * wanted < 0.0
    else:  # out of reach at this current: the most the driver gives, 1 / (4 a)
        assert applied == pytest.approx(0.25 / a)


def test_sag_command_from_the_measured_battery_voltage() -> None:
    """Without a current the battery's terminal voltage says what share the motor gets."""
    r_b, v_batt, i, wanted = 0.3, 7.2, 15.0, 3.0
    c = sag_command(wanted, r_b, v_batt, math.nan, vbat=6.5)
    assert c == pytest.approx(wanted * 7.2 / 6.5)
    # The duty the command gives on a battery at 6.5 V: the motor sees duty * 6.5.
    assert c / v_batt * 6.5 == pytest.approx(wanted)
    # No sag known, or no measurement: unchanged.
    assert sag_command(wanted, 0.0, v_batt, i) == wanted
    assert sag_command(wanted, r_b, v_batt, math.nan) == wanted
    assert sag_command(wanted, r_b, v_batt, math.nan, vbat=0.0) == wanted


def test_sag_limit_is_the_most_the_driver_applies() -> None:
    top = sag_limit(7.2, 0.3, 7.2, 10.0)
    assert top == pytest.approx(7.2 - 0.3 * 10.0)
    assert sag_limit(7.2, 0.3, 7.2, -10.0) == 7.2
    assert sag_limit(7.2, 0.0, 7.2, 10.0) == 7.2


@pytest.mark.parametrize("threshold,offset", [(1.2, 0.0), (0.0, 0.8), (1.5, 0.5)])
@pytest.mark.parametrize("wanted", [-5.0, -1.5, 1.0, 1.3, 2.0, 6.0])
def test_dead_zone_law_is_a_right_inverse_outside_the_zone(
    threshold: float, offset: float, wanted: float
) -> None:
    law = DeadZoneLaw(threshold, offset)
    assert law.smallest >= threshold - offset  # never below what the driver gives
    if abs(wanted) < law.smallest:
        return  # inside: see the hysteresis test
    applied, _ = driver_output(
        law.command(wanted), Effects(dead_zone=threshold, dead_zone_offset=offset), 7.2
    )
    assert applied == pytest.approx(wanted)


def test_dead_zone_law_holds_its_state_inside_the_zone() -> None:
    """A wanted voltage hovering in the zone's middle (as at creep speed) does not flip the
    command every cycle; the nearest-value rounding would."""
    law = DeadZoneLaw(1.2, margin=0.1)
    c = 1.32  # the zone with its 10 % margin
    wanted = [0.8, 0.5, 0.7, 0.45, 0.75, 0.5, 0.65, 0.55]  # around half the zone, 0.6 V
    sent = [law.command(w) for w in wanted]
    assert sent == pytest.approx([c] * len(wanted))
    rounded = [dead_zone_command(w, 1.2) for w in wanted]
    assert len(set(rounded)) == 2  # what the hysteresis avoids
    # Off below 30 % of the zone, on again above 60 %, holding in between.
    got = [law.command(w) for w in (0.3, 0.5, 0.8, 0.5, 0.0)]
    assert got == pytest.approx([0.0, 0.0, c, c, 0.0])
    # The other direction, and a sign change switches off first.
    assert [law.command(w) for w in (-0.8, -0.5, 0.5)] == pytest.approx([-c, -c, 0.0])
    # A wanted voltage just above the zone is sent with the margin: an underestimated
    # zone (the true one 1.3 V) still applies it.
    applied, _ = driver_output(law.command(1.25), Effects(dead_zone=1.3), 7.2)
    assert applied == pytest.approx(c)


def test_unknown_effect_is_named_at_start_up() -> None:
    @dataclasses.dataclass(frozen=True)
    class Later(Effects):
        cogging_torque: float = 0.0

    assert startup_line(Effects(load_force=2.0, hill_force=1.0, hill_length=3.0)) is None
    later = Later(load_force=2.0, cogging_torque=0.05)
    assert unused_effects(later) == ("cogging_torque",)
    line = startup_line(later)
    assert line is not None and "cogging_torque = 0.05" in line


def test_feedforward_torque_holds_the_terrain_where_the_command_acts() -> None:
    p = load_config().vehicle
    eff = Effects(load_force=1.0, hill_force=2.0, hill_start=5.0, hill_length=1.0)
    assert feedforward_torque(p, eff, 0.5, 4.9) == pytest.approx(p.force_to_torque(1.0))
    assert feedforward_torque(p, eff, 0.5, 5.5) == pytest.approx(p.force_to_torque(3.0))


def test_delay_predictor_predicts_the_plants_speed_when_the_command_acts() -> None:
    """The state the MPC plans from, predicted over the commands in the pipeline, is the
    speed the plant has when the next command acts; the speed measured now is not."""
    tc = load_config()
    p, delay, dt = _truck(), 0.08, tc.control.period
    eff = Effects(input_delay=delay)
    ctrl = Controller(ControlModel(p, eff), tc.control, TICKS)
    plant = Plant(p, PlantConfig(effects=eff))
    plant.reset(v=0.8)
    commands = [2.6] * 40 + [4.5, 5.0, 5.5, 5.5, 5.5, 3.0, 2.0, 2.0]
    for u in commands:
        ctrl._sent.append(u)
        ctrl._wanted = ctrl._out = ctrl.u_prev = u
        plant.command(u)
        plant.advance(dt)
    v_now = plant.v
    est = Estimate(v_now, True, 2.0, v_now, True, "tracking", 0.01, 0, 0, 0, 0, x=plant.x)
    ff = ctrl._feedforward(v_now, plant.x)
    steps = round(delay / dt)
    x0, _ = ctrl._initial_state(v_now, 2.0, ff, [v_now] * steps, x_pos=est.x)
    plant.command(0.0)  # after the pipeline; nothing of it acts within the delay
    plant.advance(delay - 1e-9)
    v_then = plant.v
    assert abs(x0[1] - v_then) < 0.25 * abs(v_now - v_then)
    assert abs(v_now - v_then) > 0.05  # the pipeline's commands change the speed


def test_clean_truck_gap_error_unchanged_by_an_empty_model() -> None:
    """No effect in the model: the maps are identities (the default controller)."""
    ctrl = Controller(ControlModel(_truck()), load_config().control, TICKS)
    assert not ctrl.dead_zone.active
    assert ctrl._command(3.3) == 3.3
    assert np.isnan(ctrl.current)


def test_saturated_plan_stays_within_the_drivers_limit_without_wind_up() -> None:
    """A truck that does not speed up (here: held at 0.5 m/s) while the plan asks for the
    driver's limit: every command within the diagnosed saturation, and the offset-free
    integrator (which grows while the command ramps up) does not wind up at the limit."""
    tc = load_config()
    cfg = dataclasses.replace(tc.control, disturbance_gain=0.05)
    ctrl = Controller(ControlModel(_truck(), Effects(voltage_saturation=3.0)), cfg, TICKS)
    assert ctrl.u_max == 3.0
    est = Estimate(0.5, True, math.nan, math.nan, False, "none", math.nan, 0, 0, 0, 0)
    us, dist = [], []
    for _ in range(200):
        us.append(ctrl.control(est).u)
        dist.append(ctrl.disturbance_v)
    assert all(abs(u) <= 3.0 for u in us)
    first = next(k for k, u in enumerate(us) if u > 3.0 - SATURATED_V)
    assert min(us[first:]) > 3.0 - SATURATED_V  # at the limit from here on
    assert dist[first + 1 :] == [dist[first]] * (len(us) - first - 1)


def test_current_window_is_what_the_driver_clips_to() -> None:
    p = _truck()
    eff = Effects(current_limit=12.0)
    omega, r = 800.0, p.R_m * 1.1
    lo, hi = current_window(p, eff, omega, r)
    assert (lo, hi) == pytest.approx((p.K_v * omega - r * 12.0, p.K_v * omega + r * 12.0))
    for volts in (-7.0, lo, 0.5 * (lo + hi), 7.0):
        assert min(max(volts, lo), hi) == current_limited(p, eff, volts, omega, r)
    assert current_window(p, Effects(), omega, r) == (-math.inf, math.inf)


def test_current_limit_records_the_limited_voltage_without_wind_up() -> None:
    """A truck held at 0.5 m/s while the plan asks for the driver's top: the command goes
    out as wanted (the driver limits it at the true speed), the controller's record of the
    voltage acting is the limited one (``K_v omega + R I_max``, not the command), and the
    offset-free integrator stops while the limit binds."""
    tc = load_config()
    cfg = dataclasses.replace(tc.control, disturbance_gain=0.05)
    p = _truck()
    ctrl = Controller(ControlModel(p, Effects(current_limit=12.0)), cfg, TICKS)
    est = Estimate(0.5, True, math.nan, math.nan, False, "none", math.nan, 0, 0, 0, 0)
    top = p.K_v * p.omega(0.5) + p.R_m * 12.0
    us, acting, dist = [], [], []
    for _ in range(200):
        us.append(ctrl.control(est).u)
        acting.append(ctrl._applied_prev())
        dist.append(ctrl.disturbance_v)
    assert max(us) > top + 1.0  # the command itself is not cut
    assert max(acting) == pytest.approx(top)
    first = next(k for k, a in enumerate(acting) if a >= top - 1e-12)
    assert dist[first + 1 :] == [dist[first]] * (len(us) - first - 1)
    # Without the limit in the model the record is the command (what the seed believes).
    seed = Controller(ControlModel(p), cfg, TICKS)
    for _ in range(200):
        seed.control(est)
    assert seed._applied_prev() > top + 1.0


@pytest.mark.parametrize("v", [-0.4, 0.05, 0.1, 0.3])
def test_stribeck_feedforward_follows_the_curve(v: float) -> None:
    """Moving, the feedforward cancels ``K_coulomb + F_s exp(-(v/v_s)^2)``; the start
    breaks the curve's peak ``K_coulomb + F_s`` when it exceeds the stiction."""
    p = _truck()
    f_s, v_s = 0.02, 0.1
    eff = Effects(stribeck=f_s, stribeck_speed=v_s)
    friction = p.K_coulomb + f_s * math.exp(-((v / v_s) ** 2))
    got = moving_feedforward(p, eff, v, 0.02)
    assert got == pytest.approx(math.copysign(torque_to_voltage(p, friction), v))
    peak = p.K_coulomb + f_s
    assert peak > p.K_stiction
    assert breakaway_feedforward(p, eff, 1.1) == pytest.approx(torque_to_voltage(p, 1.1 * peak))
    assert breakaway_feedforward(p, Effects(), 1.1) == pytest.approx(
        torque_to_voltage(p, 1.1 * p.K_stiction)
    )


def test_stribeck_feedforward_holds_the_plants_speed() -> None:
    """``K_v omega + u_ff`` on a plant with Stribeck friction settles at omega (at twice
    v_s, where the curve's slope cannot destabilise the voltage-driven motor)."""
    p = _truck()
    eff = Effects(stribeck=0.02, stribeck_speed=0.1)
    v = 0.2
    plant = Plant(p, PlantConfig(effects=eff))
    plant.reset(v=v)
    plant.command(p.K_v * p.omega(v) + moving_feedforward(p, eff, v, 0.02))
    for _ in range(300):
        plant.advance(0.01)
    assert plant.v == pytest.approx(v, rel=1e-3)
    seed = Plant(p, PlantConfig(effects=eff))
    seed.reset(v=v)
    seed.command(p.K_v * p.omega(v) + moving_feedforward(p, Effects(), v, 0.02))
    for _ in range(300):
        seed.advance(0.01)
    assert seed.v < 0.95 * v  # the Coulomb-only feedforward falls short


def test_winding_model_settles_where_the_plants_winding_does() -> None:
    """At a constant current the rise settles where ``rise = R_th i^2 R_m (1 + alpha
    rise)``; the resistance follows; the quasi-static current serves without a
    measurement; without the effect the resistance stays R_m."""
    p = _truck()
    eff = Effects(resistance_drift=2.0, winding_time_constant=5.0)
    w = Winding(p, eff)
    i = 9.0
    for _ in range(10000):
        r = w.update(0.01, i)
    q = 2.0 * i * i * p.R_m
    rise = q / (1.0 - COPPER_TEMPCO * q)
    assert w.rise == pytest.approx(rise, rel=1e-6)
    assert r == pytest.approx(p.R_m * (1.0 + COPPER_TEMPCO * rise))
    # One step from cold: exact first order, at the quasi-static current of 1 V at rest.
    cold = Winding(p, eff)
    cold.update(0.5, math.nan, 1.0, 0.0)
    i_qs = 1.0 / p.R_m
    assert cold.rise == pytest.approx(2.0 * i_qs * i_qs * p.R_m * (1.0 - math.exp(-0.1)))
    off = Winding(p, Effects())
    assert off.update(0.01, 30.0) == p.R_m and off.rise == 0.0
    # A wrong current reading cannot heat the model beyond a winding that has burnt.
    cold.update(1.0, 1e9)
    assert cold.rise == RISE_MAX and math.isfinite(cold.resistance)
    cold.update(1.0, math.inf, math.nan, 0.0)
    assert cold.rise == RISE_MAX


def test_warm_winding_scales_the_feedforward() -> None:
    """The controller's feedforward voltages use the winding's resistance: after a long
    high current the friction feedforward is ``R / R_m`` times the cold one."""
    tc = load_config()
    p = _truck()
    eff = Effects(resistance_drift=10.0, winding_time_constant=2.0)
    ctrl = Controller(ControlModel(p, eff), tc.control, TICKS)
    ctrl.current = 8.0
    for _ in range(2000):
        ctrl._update_winding(0.5)
    cold = Controller(ControlModel(p), tc.control, TICKS)
    ratio = ctrl.winding.resistance / p.R_m
    assert ratio > 1.2
    assert ctrl._feedforward(0.5, 0.0) == pytest.approx(ratio * cold._feedforward(0.5, 0.0))
