"""Each effect switch changes the simulated truck the way its physics says."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from truckd.model.effects import ARRAYS, EFFECT_FIELDS, EFFECT_NAMES, Effects, driver_output
from truckd.model.motor import steady_speed
from truckd.model.params import VehicleParams
from truckd.sim.plant import Plant, PlantConfig, simulate_open_loop

T = np.arange(0.0, 5.0, 0.01)


def run(p: VehicleParams, u: np.ndarray, t: np.ndarray = T, **effects: float) -> np.ndarray:
    return simulate_open_loop(p, t, u, PlantConfig(effects=Effects(**effects))).v


def step(volts: float, at: float = 0.5, t: np.ndarray = T) -> np.ndarray:
    return np.where(t >= at - 1e-12, volts, 0.0)


def test_all_contract_effects_are_switches() -> None:
    assert set(EFFECT_NAMES) == {
        "viscous_friction",
        "aero_drag",
        "load_force",
        "input_delay",
        "dead_zone",
        "dead_zone_offset",
        "voltage_saturation",
        "battery_sag",
        "sensor_lag",
        "current_limit",
        "backlash",
        "stribeck",
        "resistance_drift",
    }
    assert Effects().active() == ()
    assert Effects(dead_zone=1.0, sensor_lag=0.1).active() == ("dead_zone", "sensor_lag")


def test_every_field_of_effects_is_named_once() -> None:
    """The effects, their companions and the terrain fields name every field of Effects
    exactly once: the fast simulator, the candidates and the model file follow them."""
    assert len(EFFECT_FIELDS) == len(set(EFFECT_FIELDS))
    assert set(EFFECT_FIELDS) == {f.name for f in dataclasses.fields(Effects)}


@pytest.mark.parametrize(
    "eff",
    [
        Effects(),
        Effects(dead_zone=1.3),
        Effects(dead_zone_offset=0.7, battery_sag=0.2),
        Effects(dead_zone=0.9, dead_zone_offset=0.4, voltage_saturation=4.5, battery_sag=0.1),
    ],
)
def test_the_driver_on_a_log_is_the_driver_on_each_command(eff: Effects) -> None:
    """The fast simulator calls the driver on a whole log (ARRAYS): the same numbers as
    the plant's call per command."""
    u = np.random.default_rng(5).uniform(-9.0, 9.0, 500)
    u[:4] = (0.0, eff.dead_zone, -eff.dead_zone_offset, 7.2)
    volts, r_x = driver_output(u, eff, 7.2, ARRAYS)
    each = [driver_output(x, eff, 7.2) for x in u.tolist()]
    assert volts.tolist() == [v for v, _ in each]
    assert r_x.tolist() == [r for _, r in each]


def test_input_delay_shifts_the_step_response_by_the_delay(params: VehicleParams) -> None:
    """Delay 37.5 ms (not a multiple of the 10 ms step): equals the undelayed model with the
    step moved by 37.5 ms, simulated on a 0.5 ms grid."""
    delay = 0.0375
    delayed = run(params, step(4.0, 0.5), input_delay=delay)
    fine_t = np.arange(0.0, 5.0, 0.0005)
    moved = run(params, step(4.0, 0.5 + delay, fine_t), t=fine_t)[::20]
    assert np.max(np.abs(delayed - moved)) < 1e-9
    assert np.all(delayed[T < 0.5 + delay] == 0.0)


def test_voltage_saturation_caps_the_steady_speed(params: VehicleParams) -> None:
    v = run(params, step(7.0), voltage_saturation=4.0)
    assert v[-1] == pytest.approx(params.speed(steady_speed(params, 4.0)), rel=0.005)
    assert v[-1] < 0.95 * run(params, step(7.0))[-1]


def test_dead_zone_ignores_small_commands(params: VehicleParams) -> None:
    assert np.all(run(params, step(1.5), dead_zone=2.0) == 0.0)  # 1.5 V alone would move it
    assert run(params, step(1.5))[-1] > 0.1
    np.testing.assert_allclose(run(params, step(3.0), dead_zone=2.0), run(params, step(3.0)))


def test_viscous_friction_lowers_speed_by_the_closed_form(params: VehicleParams) -> None:
    b = 2e-6  # N m s/rad
    v = run(params, step(5.0), viscous_friction=b)
    assert v[-1] == pytest.approx(params.speed(steady_speed(params, 5.0, viscous=b)), rel=0.005)


def test_aero_drag_steady_state_balances_the_quadratic(params: VehicleParams) -> None:
    c = 2.0  # N/(m/s)^2
    v = run(params, step(6.0), aero_drag=c)[-1]
    # Steady state: K_T i = K_c + c r v^2 and 6 V = R i + K_v w.
    i = (params.K_coulomb + params.force_to_torque(c * v * v)) / params.K_T
    w = (6.0 - params.R_m * i) / params.K_v
    assert v == pytest.approx(params.speed(w), rel=0.005)
    assert v < 0.9 * run(params, step(6.0))[-1]


def test_load_force_acts_in_one_direction_whatever_the_motion(params: VehicleParams) -> None:
    f = 3.0  # N opposing forward motion (uphill)
    fwd = run(params, step(4.0), load_force=f)[-1]
    back = run(params, step(-4.0), load_force=f)[-1]
    extra = params.force_to_torque(f)
    i_f = (params.K_coulomb + extra) / params.K_T
    i_b = (-params.K_coulomb + extra) / params.K_T
    assert fwd == pytest.approx(params.speed((4.0 - params.R_m * i_f) / params.K_v), rel=0.005)
    assert back == pytest.approx(params.speed((-4.0 - params.R_m * i_b) / params.K_v), rel=0.005)
    assert abs(back) > abs(fwd)


def test_load_force_larger_than_stiction_rolls_the_truck_back(params: VehicleParams) -> None:
    f = 1.5 * params.K_stiction / params.ratio  # steep hill, no power
    v = run(params, np.zeros_like(T), load_force=f)
    assert v[-1] < -0.01


def test_position_dependent_load_varies_with_position(params: VehicleParams) -> None:
    sim = simulate_open_loop(
        params,
        T,
        step(5.0),
        PlantConfig(effects=Effects(load_force_amplitude=4.0, load_force_wavelength=2.0)),
    )
    moving = sim.v[T > 2.0]
    assert moving.max() - moving.min() > 0.05  # speed ripples as the terrain passes


def test_battery_sag_is_a_current_dependent_resistance(params: VehicleParams) -> None:
    r_b = 0.05
    sim = simulate_open_loop(params, T, step(6.0), PlantConfig(effects=Effects(battery_sag=r_b)))
    duty = 6.0 / params.V_batt
    i = params.K_coulomb / params.K_T
    w = (6.0 - (params.R_m + r_b * duty**2) * i) / params.K_v
    assert sim.v[-1] == pytest.approx(params.speed(w), rel=0.005)
    start = sim.vbat[(T > 0.5) & (T < 0.6)]
    assert start.min() < params.V_batt - 0.5  # the supply droops under the start current
    assert sim.vbat[-1] == pytest.approx(params.V_batt - r_b * duty * i, rel=1e-6)


def test_sensor_lag_filters_the_measured_speed(params: VehicleParams) -> None:
    tau = 0.2
    sim = simulate_open_loop(params, T, step(4.0), PlantConfig(effects=Effects(sensor_lag=tau)))
    # Offline first-order filter of the true speed's interval means reproduces it.
    mean_v = np.diff(sim.x) / np.diff(T)
    lag = np.zeros_like(sim.v)
    for k in range(1, len(T)):
        lag[k] = lag[k - 1] + (1 - math.exp(-(T[k] - T[k - 1]) / tau)) * (
            mean_v[k - 1] - lag[k - 1]
        )
    np.testing.assert_allclose(sim.v, lag, atol=1e-12)
    assert np.all(sim.v[T < 1.0] <= sim.v_true[T < 1.0] + 1e-12)
    assert sim.v[-1] == pytest.approx(sim.v_true[-1], rel=1e-3)


def test_noise_and_encoder_quantisation(params: VehicleParams) -> None:
    noisy = simulate_open_loop(params, T, step(4.0), PlantConfig(noise_v=0.02, seed=3))
    resid = noisy.v - noisy.v_true
    assert np.std(resid) == pytest.approx(0.02, rel=0.1)
    ticks = 120
    quant = simulate_open_loop(params, T, step(4.0), PlantConfig(encoder_ticks_per_rev=ticks))
    tick_len = 2 * math.pi * params.r_w / ticks
    counts = quant.v * 0.01 / tick_len
    np.testing.assert_allclose(counts, np.round(counts), atol=1e-6)
    assert np.mean(quant.v[T > 3]) == pytest.approx(quant.v_true[-1], rel=0.01)


def test_the_noise_is_the_seeds_normals_in_reading_order(params: VehicleParams) -> None:
    """Speed then current at each reading take the generator's next standard normals,
    however many at a time the plant draws (1 000 draws here, past a block boundary)."""
    cfg = PlantConfig(noise_v=0.02, noise_i=0.3, seed=7)
    noisy = simulate_open_loop(params, T, step(4.0), cfg)
    clean = simulate_open_loop(params, T, step(4.0))
    normals = np.random.default_rng(7).standard_normal(2 * len(T))
    np.testing.assert_allclose(noisy.v - clean.v, 0.02 * normals[0::2], atol=1e-12)
    np.testing.assert_allclose(noisy.i - clean.i, 0.3 * normals[1::2], atol=1e-12)


def test_non_finite_command_is_treated_as_zero(params: VehicleParams) -> None:
    plant = Plant(params)
    plant.command(5.0)
    plant.advance(0.5)
    plant.command(float("nan"))
    plant.advance(2.0)
    assert plant.v == 0.0 and math.isfinite(plant.motor.i)


def test_current_limit_caps_the_current_and_the_acceleration(params: VehicleParams) -> None:
    """A 7 V step from rest would draw ~80 A; limited to 25 A the current stays within it
    and the truck accelerates at (K_T I - K_coulomb) / J_S while the limit binds."""
    limit = 25.0
    t = np.arange(0.0, 1.0, 0.001)
    log = simulate_open_loop(
        params, t, step(7.0, 0.1, t), PlantConfig(effects=Effects(current_limit=limit))
    )
    assert np.max(np.abs(log.i)) <= limit * 1.001
    free = simulate_open_loop(params, t, step(7.0, 0.1, t))
    assert np.max(np.abs(free.i)) > 2.0 * limit
    accel = (params.K_T * limit - params.K_coulomb) / params.J_S * params.ratio
    k0, k1 = int(0.11 / 0.001), int(0.13 / 0.001)
    measured = (log.v_true[k1] - log.v_true[k0]) / (t[k1] - t[k0])
    assert measured == pytest.approx(accel, rel=0.01)


def test_stribeck_slows_the_truck_only_at_low_speed(params: VehicleParams) -> None:
    """Friction K_coulomb + F_s exp(-(v/v_s)^2): a command that holds a slow speed holds a
    slower one; at full speed the friction excess has faded."""
    eff = {"stribeck": 0.008, "stribeck_speed": 0.15}
    slow = run(params, step(0.8), **eff)[-1]
    assert 0.0 < slow < 0.9 * run(params, step(0.8))[-1]
    fast = run(params, step(6.0), **eff)[-1]
    assert fast == pytest.approx(run(params, step(6.0))[-1], rel=1e-4)


def test_resistance_drift_heats_the_winding_to_its_steady_rise(params: VehicleParams) -> None:
    """Under a steady load the current is ``(K_coulomb + load) / K_T`` whatever R is; the
    winding settles where ``rise = R_th i^2 R_m (1 + alpha rise)``."""
    from truckd.model.effects import COPPER_TEMPCO

    load = 8.0  # N at the wheels
    eff = Effects(resistance_drift=2.0, winding_time_constant=5.0, load_force=load)
    plant = Plant(params, PlantConfig(effects=eff))
    plant.command(5.0)
    for _ in range(6000):
        plant.advance(0.01)
    i = (params.K_coulomb + params.force_to_torque(load)) / params.K_T
    q = 2.0 * i * i * params.R_m
    assert plant.winding_rise == pytest.approx(q / (1.0 - COPPER_TEMPCO * q), rel=1e-3)


def test_backlash_holds_the_load_while_the_rotor_crosses_the_gap(params: VehicleParams) -> None:
    """At rest with the gears closed forward, a reverse command turns the rotor alone
    (its inertia ``rotor_inertia_fraction J_S``, time constant ``J_r R / (K_T K_v)``)
    through the gap; the truck starts to move only when the rotor has turned by it."""
    gap, frac, volts = 2.0, 0.35, -3.0
    t = np.arange(0.0, 0.2, 0.0002)
    log = simulate_open_loop(
        params,
        t,
        step(volts, 0.0, t),
        PlantConfig(effects=Effects(backlash=gap, rotor_inertia_fraction=frac)),
    )
    tau = frac * params.J_S * params.R_m / (params.K_T * params.K_v)
    w_inf = abs(volts) / params.K_v
    grid = np.linspace(0.0, 0.1, 100001)
    turned = w_inf * (grid - tau * (1.0 - np.exp(-grid / tau)))
    t_cross = float(grid[np.argmax(turned >= gap)])
    assert np.all(log.x[t < t_cross - 0.0005] == 0.0)
    assert np.all(log.x[t > t_cross + 0.0005] < 0.0)
