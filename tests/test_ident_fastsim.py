"""The fitting loop's fast simulator against the reference plant (truckd.sim.plant).

If the two disagreed, a diagnosis of plant logs would name the disagreement as an
effect; the tolerances below are a small fraction of the 0.01 m/s sensor noise the
diagnosis tests use.
"""

from __future__ import annotations

import dataclasses
import zlib

import numpy as np
import pytest
from labkit.synth import EFFECT_RANGES, excitation, plant_log

from truckd.ident.candidates import voltage_candidates
from truckd.ident.data import Series, series_from_log
from truckd.ident.fastsim import DRIVER_FIELDS, simulate_voltage, timeline, unsupported_effects
from truckd.ident.forcerun import ForceModel, simulate_force
from truckd.ident.voltage import predict
from truckd.model.effects import ARRAYS, EFFECT_NAMES, Effects, driver_output
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

TOL_RMS = {"battery_sag": 1.5e-3, "backlash": 1.5e-3, "stribeck": 1e-3}
"""RMS speed difference allowed (m/s); battery sag changes the electrical time constant
per command, which the first-order model keeps only approximately; with backlash the
rotor crosses the gap in a few ms, and the instant it meets the load shifts by the
electrical lag the plant has (the fast model does not); the Stribeck friction is held
over a sub-interval at its midpoint speed (the plant's over 1 ms pieces)."""


def _compare(p: VehicleParams, eff: Effects, seed: int, n: int = 3000) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    t, u = excitation(rng, n)
    ref = simulate_open_loop(p, t, u, PlantConfig(effects=eff))
    fast = simulate_voltage(p, eff, t, u)
    return float(np.sqrt(np.mean((ref.v - fast.v) ** 2))), float(abs(ref.x[-1] - fast.x[-1]))


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_fast_simulator_agrees_with_plant(params: VehicleParams, name: str) -> None:
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    lo, hi = EFFECT_RANGES[name]
    eff = dataclasses.replace(Effects(), **{name: float(rng.uniform(lo, hi))})
    err, dx = _compare(params, eff, seed=int(rng.integers(1 << 30)))
    assert err < TOL_RMS.get(name, 3e-4), f"{name}: rms {err:.2e} m/s"
    assert dx < 0.02, f"{name}: position differs by {dx:.3g} m after 30 s"


def test_fast_simulator_agrees_with_plant_on_backlash_behind_a_current_limit(
    params: VehicleParams,
) -> None:
    """The rotor crossing the gap is driven within the current limit, as in the plant
    (the fast model drove it with the unlimited voltage: 0.083 m/s RMS apart, six noise
    units of a drawn truck's log, and the pair could not be fitted)."""
    eff = Effects(backlash=3.0, rotor_inertia_fraction=0.35, current_limit=28.0)
    err, dx = _compare(params, eff, seed=1)
    assert err < TOL_RMS["backlash"], f"rms {err:.2e} m/s"
    assert dx < 0.02, f"position differs by {dx:.3g} m after 30 s"


def test_fast_simulator_agrees_without_effects(params: VehicleParams) -> None:
    err, _ = _compare(params, Effects(), seed=7)
    assert err < 3e-4


def test_current_prediction_matches_plant(params: VehicleParams) -> None:
    rng = np.random.default_rng(3)
    t, u = excitation(rng, 2000)
    ref = simulate_open_loop(params, t, u)
    fast = simulate_voltage(params, Effects(), t, u)
    err = np.sqrt(np.mean((ref.i[1:] - fast.i[1:]) ** 2))
    assert err < 0.02 * np.std(ref.i)


def test_delay_between_samples_is_split_exactly(params: VehicleParams) -> None:
    """A delay of 1.37 samples: the fast simulator splits steps where the plant does."""
    t = np.arange(400) * 0.01
    u = np.where((t > 0.5) & (t < 2.0), 5.0, -3.0)
    eff = Effects(input_delay=0.0137)
    ref = simulate_open_loop(params, t, u, PlantConfig(effects=eff))
    fast = simulate_voltage(params, eff, t, u)
    rounded = simulate_voltage(params, Effects(input_delay=0.01), t, u)
    err = np.max(np.abs(ref.v - fast.v))
    assert err < 2e-3
    assert np.max(np.abs(ref.v - rounded.v)) > 5 * err  # the fraction of a step matters


def test_history_makes_a_chunk_equal_to_the_whole(params: VehicleParams) -> None:
    """Commands issued before a chunk still act inside it when there is a delay."""
    rng = np.random.default_rng(5)
    t, u = excitation(rng, 1500)
    eff = Effects(input_delay=0.043)
    whole = simulate_voltage(params, eff, t, u)
    k = 700
    part = Series(t=t, inp=u, v=whole.v).slice(k, 1500)
    assert part.hist_t is not None and part.hist_inp is not None
    chunk = simulate_voltage(
        params, eff, part.t, part.inp, float(whole.v[k]), part.hist_t, part.hist_inp
    )
    no_hist = simulate_voltage(params, eff, part.t, part.inp, float(whole.v[k]))
    assert np.max(np.abs(chunk.v - whole.v[k:])) < 1e-3
    assert np.max(np.abs(no_hist.v - whole.v[k:])) > 1e-2


def test_timeline_covers_the_log_once() -> None:
    t = np.cumsum(np.full(50, 0.01)) - 0.01
    for delay in (0.0, 0.004, 0.01, 0.0237):
        tl = timeline(t, delay)
        assert np.isclose(tl.dt.sum(), t[-1] - t[0])
        assert list(tl.sample_end[tl.sample_end >= 0]) == list(range(1, 50))
        assert np.all(tl.dt > 0)


def test_force_model_matches_closed_form() -> None:
    """M dv/dt = F - F_v v - F_c (sliding forward) has v(t) = v_inf (1 - exp(-t F_v/M))."""
    m = ForceModel(M=2.0, F_c=1.0, F_v=4.0, offset=0.5)
    t = np.linspace(0.0, 2.0, 201)
    f = np.full_like(t, 10.0)
    v, x = simulate_force(m, t, f)
    v_inf = (10.0 - 1.0 - 0.5) / 4.0
    expect = v_inf * (1.0 - np.exp(-t * 4.0 / 2.0))
    assert np.max(np.abs(v - expect)) < 1e-9
    x_expect = v_inf * (t - (1.0 - np.exp(-2.0 * t)) / 2.0)
    assert np.max(np.abs(x - x_expect)) < 1e-9


def test_force_model_sticks_below_breakaway() -> None:
    m = ForceModel(M=1.0, F_c=2.0, F_v=1.0)
    t = np.linspace(0.0, 1.0, 101)
    v, _ = simulate_force(m, t, np.full_like(t, 1.9))
    assert np.all(v == 0.0)
    v, _ = simulate_force(m, t, np.full_like(t, 2.1))
    assert v[-1] > 0.0


@pytest.mark.parametrize("with_current", [True, False])
def test_log_starting_mid_motion_under_a_delay(params: VehicleParams, with_current: bool) -> None:
    """A log that starts mid-motion: the commands before it still act for the delay.

    A delay of exactly 3 samples; the log's first command is far from the one still
    acting.  Assuming 0 V before the log's first command acts braked the truck: a
    0.2 m/s transient, 8e-3 m/s RMS over the 60 s (as much as the sensor noise).
    """
    rng = np.random.default_rng(123)
    t = np.arange(0, 120, 0.01)
    u = np.clip(rng.uniform(-6, 6, 240).repeat(50)[: len(t)] + np.sin(2 * np.pi * 0.3 * t), -7, 7)
    eff = Effects(input_delay=0.03)
    ref = simulate_open_loop(params, t, u, PlantConfig(effects=eff))
    n = len(t) // 2  # t = 60 s
    assert abs(ref.v[n]) > 0.5 and abs(u[n] - u[n - 1]) > 5.0
    second = Series(t=t[n:], inp=u[n:], v=ref.v[n:], i=ref.i[n:] if with_current else None)
    pred = predict(params, eff, second)
    err = float(np.sqrt(np.mean((pred.v - ref.v[n:]) ** 2)))
    assert err < 5e-4, f"rms {err:.2e} m/s"


@pytest.mark.parametrize(
    "eff",
    [
        Effects(load_force_amplitude=2.0, load_force_wavelength=1.5),
        Effects(hill_force=3.0, hill_start=0.5, hill_length=1.0),
        Effects(hill_force=-2.0, hill_start=-1.0, hill_length=0.8, load_force=0.5),
    ],
    ids=["rolling", "hill", "downhill"],
)
def test_fast_simulator_agrees_with_plant_on_terrain(params: VehicleParams, eff: Effects) -> None:
    """A position-dependent load (rolling terrain, a hill) is simulated as the plant does,
    and it matters (without it the run differs)."""
    rng = np.random.default_rng(11)
    t, u = excitation(rng, 1500)
    ref = simulate_open_loop(params, t, u, PlantConfig(effects=eff))
    fast = simulate_voltage(params, eff, t, u)
    flat = simulate_voltage(params, Effects(load_force=eff.load_force), t, u)
    err = float(np.sqrt(np.mean((ref.v - fast.v) ** 2)))
    assert err < 2e-3, f"rms {err:.2e} m/s"
    assert float(np.sqrt(np.mean((ref.v - flat.v) ** 2))) > 10 * err


def test_fast_simulator_starts_terrain_at_the_given_position(params: VehicleParams) -> None:
    """``x0`` places a chunk on the road: a chunk started mid-log matches the whole run."""
    rng = np.random.default_rng(12)
    t, u = excitation(rng, 1500)
    eff = Effects(hill_force=3.0, hill_start=0.3, hill_length=1.0)
    whole = simulate_voltage(params, eff, t, u)
    k = 600
    v0, pre = float(whole.v[k]), float(u[k - 1])
    part = simulate_voltage(params, eff, t[k:], u[k:], v0, v_pre=pre, x0=float(whole.x[k]))
    at_zero = simulate_voltage(params, eff, t[k:], u[k:], v0, v_pre=pre)
    assert np.max(np.abs(part.v - whole.v[k:])) < 1e-3
    assert np.max(np.abs(at_zero.v - whole.v[k:])) > 1e-2


def test_the_fast_simulator_models_every_field_of_the_effects() -> None:
    """What the fast simulator models comes from truckd.model.effects: every field of
    Effects switched on at once is accepted (a field it did not know would be refused)."""
    every = Effects(**{f.name: 0.5 for f in dataclasses.fields(Effects)})
    assert unsupported_effects(every) == []


def test_every_effect_is_a_candidate_of_the_diagnosis(params: VehicleParams) -> None:
    """Each effect of EFFECT_NAMES is tried by the diagnosis (a log with current and
    several command levels: no candidate is left out for want of data)."""
    log = plant_log(params, Effects(), seed=4, n=3000)
    names = {c.param.name for c in voltage_candidates(params, series_from_log(log))}
    assert set(EFFECT_NAMES) <= names


def test_driver_output_reads_only_the_fields_its_cache_keys_on(params: VehicleParams) -> None:
    """The fast simulator keeps the driver's output per series, battery voltage and
    DRIVER_FIELDS: changing any other field of the effects must not change it."""
    u = np.linspace(-20.0, 20.0, 81)
    base = Effects(dead_zone=0.4, dead_zone_offset=0.2, voltage_saturation=9.0, battery_sag=0.05)
    ref = driver_output(u, base, params.V_batt, ARRAYS)
    for f in dataclasses.fields(Effects):
        if f.name in DRIVER_FIELDS:
            continue
        moved = dataclasses.replace(base, **{f.name: float(getattr(base, f.name)) + 0.37})
        out = driver_output(u, moved, params.V_batt, ARRAYS)
        assert np.array_equal(out[0], ref[0]) and np.array_equal(out[1], ref[1]), f.name


def test_cached_run_inputs_give_the_same_prediction(params: VehicleParams) -> None:
    """A run after another on the same series (driver, currents' timing and settling
    kept) equals the run on a fresh copy of the series, bit for bit, current included."""
    log = plant_log(params, Effects(input_delay=0.012), seed=4, n=600)
    s = series_from_log(log)
    e1 = Effects(input_delay=0.012, dead_zone=0.3)
    e2 = dataclasses.replace(e1, viscous_friction=1e-4)
    predict(params, e1, s)
    again = predict(params, e2, s)
    fresh = predict(params, e2, dataclasses.replace(s, t=s.t.copy(), inp=s.inp.copy()))
    for got, want in ((again.v, fresh.v), (again.i, fresh.i), (again.volts, fresh.volts)):
        assert np.array_equal(got, want)
