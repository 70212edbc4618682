"""The controller uses every effect of its model: closed loop per effect on a truck unlike
the shipped one, the extended model against the seed model on the same plant and seed;
and the pieces (the delay predictor, the battery sag map, the dead-zone law, the table)
on known inputs."""

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
    DeadZoneLaw,
    feedforward_torque,
    sag_command,
    sag_limit,
    startup_line,
    unused_effects,
)
from truckd.control.estimator import Estimate
from truckd.control.feedforward import dead_zone_command
from truckd.control.qp import ControlModel
from truckd.model.effects import EFFECT_NAMES, Effects, driver_output
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
}


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
    if s - clean > 0.002:
        assert (s - e) / (s - clean) >= 0.5, (name, clean, s, e)


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
