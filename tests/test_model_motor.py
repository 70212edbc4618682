"""The seed model's physics: closed forms, stiction, exactness against a reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_integrator import reference_run

from truckd.model.motor import steady_speed
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop


def stiction_voltage(p: VehicleParams) -> float:
    """Voltage whose stalled current just makes the stiction torque (V)."""
    return p.K_stiction / p.K_T * p.R_m


@pytest.mark.parametrize("volts", [1.0, 3.0, 6.5, -2.0, -7.0])
def test_steady_speed_equals_closed_form(params: VehicleParams, volts: float) -> None:
    t = np.arange(0.0, 4.0, 0.01)
    sim = simulate_open_loop(params, t, np.full_like(t, volts))
    # Closed form from the equations: i = K_c/K_T sign(w), w = (V - R i) / K_v.
    i_ss = math.copysign(params.K_coulomb / params.K_T, volts)
    v_expected = params.speed((volts - params.R_m * i_ss) / params.K_v)
    assert sim.v[-1] == pytest.approx(v_expected, rel=0.005)
    assert sim.i[-1] == pytest.approx(i_ss, rel=0.005)
    assert params.speed(steady_speed(params, volts)) == pytest.approx(v_expected, rel=1e-12)


def test_below_stiction_stays_exactly_at_rest(params: VehicleParams) -> None:
    t = np.arange(0.0, 5.0, 0.01)
    for sign in (1.0, -1.0):
        sim = simulate_open_loop(
            params, t, np.full_like(t, sign * 0.999 * stiction_voltage(params))
        )
        assert np.all(sim.v == 0.0), "no creeping below stiction"
        assert np.all(sim.x == 0.0)


def test_just_above_stiction_moves_in_the_direction_of_the_torque(params: VehicleParams) -> None:
    t = np.arange(0.0, 5.0, 0.01)
    for sign in (1.0, -1.0):
        sim = simulate_open_loop(params, t, np.full_like(t, sign * 1.01 * stiction_voltage(params)))
        assert sign * sim.v[-1] > 0.01
        assert np.all(sign * sim.v >= 0.0)


def test_stops_and_sticks_without_chatter(params: VehicleParams) -> None:
    """Drive, then drop to a voltage that holds below stiction: speed reaches exactly 0 and
    stays there (no sign flips around zero)."""
    t = np.arange(0.0, 6.0, 0.01)
    u = np.where(t < 2.0, 4.0, 0.3 * stiction_voltage(params))
    sim = simulate_open_loop(params, t, u)
    after = sim.v[t > 3.0]
    assert np.all(after == 0.0)
    assert np.all(sim.v >= 0.0)


def test_reversal_passes_through_zero_and_breaks_away_again(params: VehicleParams) -> None:
    t = np.arange(0.0, 4.0, 0.01)
    u = np.where(t < 2.0, 5.0, -5.0)
    sim = simulate_open_loop(params, t, u)
    assert sim.v[190] > 1.0 and sim.v[-1] < -1.0
    v_expected = params.speed(steady_speed(params, -5.0))
    assert sim.v[-1] == pytest.approx(v_expected, rel=0.005)


def rich_input(rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """Steps, a multisine, stops below stiction and reversals (V)."""
    steps = rng.uniform(-6.0, 6.0, size=len(t) // 40 + 1).repeat(40)[: len(t)]
    sine = 1.5 * np.sin(2 * np.pi * 0.7 * t) + 0.8 * np.sin(2 * np.pi * 3.1 * t)
    u = steps + sine
    u[(t > 1.0) & (t < 1.6)] = 0.2  # hold below stiction: must come to rest and stick
    return np.clip(u, -7.2, 7.2)


def test_exact_discretisation_matches_fine_reference(params: VehicleParams) -> None:
    """Exact ZOH with events against an adaptive stiff integrator with events: the
    speed error stays below 0.1 % of full scale over a rich input."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 3.0, 0.01)
    u = rich_input(rng, t)
    sim = simulate_open_loop(params, t, u)
    ref = reference_run(params, t, u)
    full_scale = params.speed(steady_speed(params, params.V_batt))
    err = np.max(np.abs(sim.v - ref))
    assert err < 1e-3 * full_scale, f"max error {err:.2e} m/s"
    assert np.any(ref == 0.0) and np.any(ref > 0.5) and np.any(ref < -0.5)  # rich enough


def test_explicit_euler_at_control_rate_is_wrong(params: VehicleParams) -> None:
    """Why the exact ZOH: Euler at 10 ms diverges on the sub-millisecond electrical pole."""
    h, volts = 0.01, 3.0
    i, w = 0.0, 0.0
    for _ in range(50):
        di = (volts - params.R_m * i - params.K_v * w) / params.L_m
        dw = (params.K_T * i - params.K_coulomb * (1.0 if w > 0 else 0.0)) / params.J_S
        i, w = i + h * di, w + h * dw
    assert not math.isfinite(w) or abs(params.speed(w)) > 100.0


@given(
    seq=st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=5, max_size=60),
    dts=st.lists(st.floats(1e-4, 0.05), min_size=5, max_size=60),
)
@settings(max_examples=60, deadline=None)
def test_state_stays_finite_and_bounded(
    params: VehicleParams, seq: list[float], dts: list[float]
) -> None:
    """Any command sequence and jittered sampling: finite state, speed within the no-load
    speed at the battery voltage (the driver clips the command)."""
    n = min(len(seq), len(dts))
    t = np.concatenate([[0.0], np.cumsum(dts[: n - 1])])
    sim = simulate_open_loop(params, t, np.array(seq[:n]), PlantConfig())
    v_max = params.speed(params.V_batt / params.K_v)
    assert np.all(np.isfinite(sim.v)) and np.all(np.isfinite(sim.i))
    assert np.all(np.abs(sim.v) <= v_max * (1 + 1e-9))
