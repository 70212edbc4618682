"""Friction feedforward: it cancels Coulomb friction exactly at steady state, breaks
stiction, and in closed loop beats no feedforward on the same plant."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from truckd.config.truck import load_config
from truckd.control.config import ControlConfig
from truckd.control.feedforward import (
    breakaway_feedforward,
    dead_zone_command,
    moving_feedforward,
    torque_to_voltage,
)
from truckd.control.qp import ControlModel
from truckd.model.effects import Effects, driver_output
from truckd.model.motor import steady_speed
from truckd.model.params import VehicleParams
from truckd.sim.closed_loop import SimSetup, Trace, run_scenario
from truckd.sim.scenarios import make_scenario


@pytest.mark.parametrize("v", [0.2, 1.0, 2.2, -1.0])
def test_moving_feedforward_restores_the_friction_free_steady_speed(
    params: VehicleParams, v: float
) -> None:
    """With u = K_v omega + u_ff the friction plant runs exactly at omega."""
    omega = params.omega(v)
    u_ff = moving_feedforward(params, Effects(), v, 0.02)
    assert u_ff == pytest.approx(np.sign(v) * params.R_m / params.K_T * params.K_coulomb)
    assert steady_speed(params, params.K_v * omega + u_ff) == pytest.approx(omega, rel=1e-12)


def test_feedforward_is_zero_at_rest_and_breakaway_exceeds_stiction(
    params: VehicleParams,
) -> None:
    assert moving_feedforward(params, Effects(), 0.01, 0.02) == 0.0
    u_b = breakaway_feedforward(params, Effects(), 1.1)
    stall_torque = params.K_T * u_b / params.R_m
    assert stall_torque > params.K_stiction
    assert u_b == pytest.approx(1.1 * torque_to_voltage(params, params.K_stiction))


def test_known_effects_enter_the_feedforward(params: VehicleParams) -> None:
    eff = Effects(load_force=2.0, aero_drag=0.5, dead_zone=0.3)
    v = 1.5
    base = moving_feedforward(params, Effects(), v, 0.02)
    force = 2.0 + 0.5 * v * v
    expected = base + torque_to_voltage(params, params.force_to_torque(force))
    # The dead zone is not an offset: the driver passes commands above it unchanged.
    assert moving_feedforward(params, eff, v, 0.02) == pytest.approx(expected)


@pytest.mark.parametrize(
    ("wanted", "sent"),
    [
        (0.0, 0.0),
        (0.2, 0.0),
        (-0.59, 0.0),
        (0.6, 1.2),
        (-0.9, -1.2),
        (1.2, 1.2),
        (3.0, 3.0),
        (-5.0, -5.0),
    ],
)
def test_dead_zone_command_sends_the_nearest_voltage_the_driver_applies(
    wanted: float, sent: float
) -> None:
    assert dead_zone_command(wanted, 1.2) == sent
    applied, _ = driver_output(dead_zone_command(wanted, 1.2), Effects(dead_zone=1.2), 7.2)
    # What the driver applies is the best it can do for the wanted voltage.
    assert abs(applied - wanted) <= min(abs(wanted), abs(abs(wanted) - 1.2)) + 1e-12


def _run(name: str, feedforward: bool, duration: float) -> tuple[dict[str, Any], Trace]:
    tc = load_config()
    cfg = dataclasses.replace(ControlConfig(), feedforward=feedforward)
    setup = SimSetup(tc.vehicle, tc.plant, cfg, ControlModel(tc.vehicle))
    return run_scenario(make_scenario(name, tc.vehicle, cfg), setup, duration)


def test_feedforward_on_beats_off_at_steady_state() -> None:
    on, _ = _run("follow", True, 15.0)
    off, _ = _run("follow", False, 15.0)
    err_on = abs(on["final_gap_error_m"])
    err_off = abs(off["final_gap_error_m"])
    # Without it the friction-free MPC settles where its gap error buys the Coulomb
    # voltage (about 3 cm here); with it the error is quantisation-level.
    assert err_on < 0.005
    assert err_off > 5 * err_on
    assert on["gap_error_rms_m"] < off["gap_error_rms_m"]


def test_feedforward_on_starts_sooner_after_the_lead_goes() -> None:
    """Stop-and-go: the lead waits, then goes; with the breakaway feedforward the truck
    leaves stiction sooner (the friction-free MPC alone has to wind up past 0.65 V)."""
    cfg = load_config()
    sc = make_scenario("stop-and-go", cfg.vehicle, cfg.control)
    assert sc.lead is not None
    t_go = sc.lead.times[3]  # the lead's first start
    lags = {}
    for ff in (True, False):
        _, tr = _run("stop-and-go", ff, t_go + 2.0)
        t, v = np.array(tr.t), np.array(tr.v)
        assert np.all(v[(t > t_go - 0.15) & (t <= t_go)] < 0.01)  # at rest before
        lags[ff] = float(t[np.argmax((t > t_go) & (v > 0.02))] - t_go)
    assert 0.0 < lags[True] < lags[False]


def test_offset_free_action_removes_the_error_of_an_unknown_load() -> None:
    """A 3 N load the controller's model lacks: without the disturbance integrator the gap
    settles centimetres off, with it (gain 0.01 per cycle) at the reference."""
    tc = load_config()
    plant = dataclasses.replace(tc.plant, effects=Effects(load_force=3.0))
    errors = {}
    for gain in (0.0, 0.01):
        cfg = dataclasses.replace(tc.control, disturbance_gain=gain)
        setup = SimSetup(tc.vehicle, plant, cfg, ControlModel(tc.vehicle))
        m, _ = run_scenario(make_scenario("follow", tc.vehicle, cfg), setup, 12.0)
        errors[gain] = abs(m["final_gap_error_m"])
    assert errors[0.01] < 0.002
    assert errors[0.0] > 0.005


def test_offset_free_action_removes_the_error_of_an_unknown_load_behind_a_dead_time() -> None:
    """The same 3 N load behind a 0.15 s dead time the model knows: the integrator compares
    the measured speed with the one predicted a period ahead through the pipeline (the
    plan starts where its first move acts, 0.15 s later; compared with the plan's own next
    speed the gap error RMS was 0.44 m, nine times that without the integrator)."""
    tc = load_config()
    plant = dataclasses.replace(tc.plant, effects=Effects(load_force=3.0, input_delay=0.15))
    model = ControlModel(tc.vehicle, Effects(input_delay=0.15))
    rms, final = {}, {}
    for gain in (0.0, 0.01):
        cfg = dataclasses.replace(tc.control, disturbance_gain=gain)
        m, _ = run_scenario(
            make_scenario("follow", tc.vehicle, cfg), SimSetup(tc.vehicle, plant, cfg, model), 12.0
        )
        rms[gain], final[gain] = m["gap_error_rms_m"], abs(m["final_gap_error_m"])
    assert final[0.01] < 0.002 and rms[0.01] < 0.005, (final, rms)
    assert final[0.0] > 0.02 and rms[0.0] > 0.02, (final, rms)


def test_known_dead_zone_helps_instead_of_hurting() -> None:
    """Plant with a 1.2 V driver dead zone: the controller that knows it keeps a smaller gap
    error in stop-and-go than the seed model (it used to add the zone as an offset and lose)."""
    tc = load_config()
    cfg = ControlConfig()
    plant = dataclasses.replace(tc.plant, effects=Effects(dead_zone=1.2))
    rms = {}
    for label, eff in (("seed", Effects()), ("known", Effects(dead_zone=1.2))):
        setup = SimSetup(tc.vehicle, plant, cfg, ControlModel(tc.vehicle, eff))
        metrics, _ = run_scenario(make_scenario("stop-and-go", tc.vehicle, cfg), setup, 25.0)
        assert not metrics["collision"]
        rms[label] = metrics["gap_error_rms_m"]
    assert rms["known"] < 0.85 * rms["seed"]


@pytest.mark.parametrize("wanted", [0.0, 0.05, -0.3, 1.0, -2.5, 4.0])
def test_offset_dead_zone_command_makes_the_driver_apply_the_wanted_voltage(
    wanted: float,
) -> None:
    """Textbook form (output ``c - sign(c) 1.2``): the command adds the offset back."""
    eff = Effects(dead_zone_offset=1.2)
    sent = dead_zone_command(wanted, 0.0, 1.2)
    assert abs(sent) == (abs(wanted) + 1.2 if wanted else 0.0)
    applied, _ = driver_output(sent, eff, 7.2)
    assert applied == pytest.approx(wanted, abs=1e-12)


@pytest.mark.parametrize("wanted", [0.1, 0.3, -0.4, 0.6, 2.0])
def test_both_dead_zone_forms_send_the_nearest_voltage_the_driver_applies(
    wanted: float,
) -> None:
    """Threshold 1.5 V and offset 1.0 V: the driver applies 0 or at least 0.5 V."""
    eff = Effects(dead_zone=1.5, dead_zone_offset=1.0)
    applied, _ = driver_output(dead_zone_command(wanted, 1.5, 1.0), eff, 7.2)
    best = min(abs(wanted), abs(abs(wanted) - 0.5)) if abs(wanted) < 0.5 else 0.0
    assert abs(applied - wanted) <= best + 1e-12
