"""What a free run costs around the C kernel, without changing what it computes: the
arrays' addresses (kept for the arrays used last, a timeline's known from its block),
the fit's residuals at its solution taken from the solver, the true speed and position
computed when read, the dead zones that give the same runs run once."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from labkit.synth import draw_truck, plant_log

from truckd.config.truck import load_config
from truckd.ident import ckernel, fastsim, voltage
from truckd.ident.data import Series
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def test_the_kernel_is_there() -> None:
    """Without the kernel nothing below runs the paths it checks."""
    assert ckernel.available(), f"{ckernel.LIBRARY} missing: run `make firmware`"


def test_an_address_is_the_arrays_data_whatever_the_array() -> None:
    block = np.arange(30.0).reshape(3, 10)
    frozen = np.arange(5.0)
    frozen.flags.writeable = False
    ints = np.arange(7, dtype=np.int64)
    for a in (block, block[1], block[2, 3:], frozen, ints, ints[2:], np.empty(0)):
        assert ckernel._data(a) == a.ctypes.data


def test_the_arrays_used_last_keep_their_address(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fit's coefficients and timelines stay while each run's own arrays pass through:
    the least recently used go first (dropping the oldest stored would drop them)."""
    monkeypatch.setattr(ckernel, "_ADDRESSES", {})
    looked_up: list[int] = []
    data = ckernel._data

    def counted(a: np.ndarray) -> int:
        looked_up.append(id(a))
        return data(a)

    monkeypatch.setattr(ckernel, "_data", counted)
    kept = np.arange(10.0)
    passing = [np.arange(10.0) for _ in range(3 * ckernel.ADDRESSES_KEPT)]
    for a in passing:
        assert ckernel._address(kept) == kept.ctypes.data
        assert ckernel._address(a) == a.ctypes.data
    assert looked_up.count(id(kept)) == 1
    assert len(ckernel._ADDRESSES) == ckernel.ADDRESSES_KEPT


def _truck_log(k: int, eff: Effects) -> tuple[VehicleParams, Series]:
    p = draw_truck(load_config().vehicle, np.random.default_rng(700 + k)).params
    c = plant_log(p, eff, seed=k, n=1200).columns
    return p, Series(t=c["t"], inp=c["u"], v=c["v"], i=c.get("i"), x=None)


def test_a_timelines_addresses_are_known_from_its_block(monkeypatch: pytest.MonkeyPatch) -> None:
    """The merged timeline's three arrays are views of one block: the run that follows
    reads their addresses without converting them again, and they are the right ones."""
    p, s = _truck_log(0, Effects(input_delay=0.02))
    got: list[tuple[np.ndarray, ...]] = []
    converted: list[np.ndarray] = []  # the arrays themselves: an id can be reused
    merge, data = ckernel.shift_merge, ckernel._data

    def kept(*a: object) -> object:
        out = merge(*a)  # type: ignore[arg-type]
        if out is not None:
            got.append(out)
        return out

    def counted(a: np.ndarray) -> int:
        converted.append(a)
        return data(a)

    monkeypatch.setattr(ckernel, "shift_merge", kept)
    monkeypatch.setattr(ckernel, "_data", counted)
    for scale in (1.0123, 1.0456):  # the first run lays the series out, the next merge in C
        fastsim.predict(p.replace(J_S=p.J_S * scale), Effects(input_delay=0.02), s)
    assert got, "the run did not merge its timeline in C"
    assert converted  # the count sees conversions (the run's own block)
    for view in got[-1]:
        assert not any(a is view for a in converted)
        assert ckernel._address(view) == view.ctypes.data


@pytest.mark.parametrize("k", range(4))
def test_a_fits_residuals_are_those_at_its_solution(k: int) -> None:
    """The fit's sum of squares is the one a free run of its result gives, bit for bit."""
    eff = (Effects(), Effects(input_delay=0.02), Effects(battery_sag=0.2), Effects(load_force=1.0))[
        k
    ]
    p, s = _truck_log(k, eff)
    data = [s.slice(lo, lo + 300) for lo in range(0, 1200, 300)]
    w = voltage.weights_for(data)
    start = p.replace(J_S=p.J_S * 1.3, K_v=p.K_v * 0.9)
    free = voltage.seed_params(start, with_current=False)
    got = voltage.fit(start, eff, free, data, w)
    assert got.nfev > 1  # the solver moved
    r = voltage.residuals(got.params, got.effects, data, w)
    assert got.sse == float(r @ r) and got.n == len(r)


def test_the_true_speed_and_position_are_the_rotors_in_metres() -> None:
    p, s = _truck_log(5, Effects(sensor_lag=0.05))
    pred = fastsim.predict(p, Effects(sensor_lag=0.05), s)
    assert np.array_equal(pred.v_true, pred.rotor_speed * p.ratio)
    assert np.array_equal(pred.x, pred.rotor_angle * p.ratio)
    assert not np.array_equal(pred.v, pred.v_true)  # the lag: the sensor's speed differs


def _stepped(k: int) -> tuple[VehicleParams, list[Series]]:
    """A drawn truck driven through many small command levels (ramps' worth), in chunks."""
    p = draw_truck(load_config().vehicle, np.random.default_rng(800 + k)).params
    c = plant_log(p, Effects(dead_zone=0.8), seed=k, n=1600).columns
    s = Series(t=c["t"], inp=c["u"], v=c["v"], i=None, x=None)
    return p, [s.slice(lo, lo + 400) for lo in range(0, 1600, 400)]


@pytest.mark.parametrize("k", range(3))
def test_dead_zones_that_zero_the_same_commands_give_the_same_runs(k: int) -> None:
    p, data = _stepped(k)
    w = voltage.weights_for(data)
    key = voltage.same_runs("dead_zone", data)
    assert key is not None and voltage.same_runs("load_force", data) is None
    cut_from = [s.origin.inp for s in data if s.origin is not None]
    u = np.abs(np.concatenate([x for s in data for x in (s.hist_inp, s.inp) if x is not None]))
    u = np.concatenate([u, *(np.abs(x) for x in cut_from)])
    grid = np.linspace(0.0, float(np.max(u)), 60)
    groups: dict[int, list[float]] = {}
    for g in grid:
        groups.setdefault(key(float(g)), []).append(float(g))
        assert key(float(g)) == int(np.count_nonzero(u < g))  # the commands it zeroes
    shared = [vals for vals in groups.values() if len(vals) > 1]
    assert shared and len(groups) > 3  # the grid has both: values alike and values apart
    for vals in shared:
        runs = [voltage.residuals(p, Effects(dead_zone=v), data, w) for v in vals]
        assert all(np.array_equal(r, runs[0]) for r in runs[1:])


def test_a_dead_zone_scan_runs_each_set_of_zeroed_commands_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The same choice and cost as running every value, with fewer free runs."""
    p, data = _stepped(0)
    w = voltage.weights_for(data)
    u = np.abs(np.concatenate([s.inp for s in data]))
    grid = tuple(float(g) for g in np.linspace(0.0, float(np.max(u)), 80))
    calls = {"n": 0}
    residuals = voltage.residuals

    def counted(*a: object) -> np.ndarray:
        calls["n"] += 1
        return residuals(*a)  # type: ignore[arg-type]

    monkeypatch.setattr(voltage, "residuals", counted)
    grouped = voltage.scan(p, Effects(), "dead_zone", grid, data, w, coarse=200)
    runs_grouped = calls["n"]
    calls["n"] = 0
    monkeypatch.setattr(voltage, "same_runs", lambda name, data: None)
    every = voltage.scan(p, Effects(), "dead_zone", grid, data, w, coarse=200)
    assert grouped == every
    assert runs_grouped < calls["n"] == len(grid)


def test_the_commands_of_the_run_a_stretch_was_cut_from_count() -> None:
    """With a winding's drift, a stretch starts as warm as the run before it made the
    winding: a dead zone that zeroes a command only there changes the stretch's run."""
    p = load_config().vehicle
    t = np.arange(4000) * 0.005
    u = np.where(t < 10.0, 3.0, 5.0)
    whole = Series(t=t, inp=u, v=np.zeros_like(t), i=None, x=None)
    data = [whole.slice(lo, lo + 500) for lo in (3000, 3500)]  # 5 V only, history too
    eff = Effects(resistance_drift=3.0, winding_time_constant=20.0)
    w = voltage.Weights(v=1.0)
    key = voltage.same_runs("dead_zone", data)
    assert key is not None and key(2.0) != key(4.0)  # 3 V, before the stretches, between
    a = voltage.residuals(p, dataclasses.replace(eff, dead_zone=2.0), data, w)
    b = voltage.residuals(p, dataclasses.replace(eff, dead_zone=4.0), data, w)
    assert not np.array_equal(a, b)
