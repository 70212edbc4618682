"""The fitting engine's exact shortcuts: a free run tells which stiction torques give the
same run (the stiction scan reuses it), the terrain's first-order filter in C is scipy's,
and the electrical correction at R_m in floats is the array form's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from labkit.synth import draw_truck, plant_log
from scipy.signal import lfilter

from truckd.config.truck import load_config
from truckd.ident import ckernel, fastsim, freerun, prediction, voltage
from truckd.ident.data import Series
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

# Effects under which the breakaway threshold is the run's sigma throughout (no
# per-command scale, no Stribeck friction, no backlash): the band is known.
BANDED = [
    Effects(),
    Effects(input_delay=0.027, sensor_lag=0.03),
    Effects(dead_zone=1.2, voltage_saturation=5.0, load_force=2.0),
    Effects(current_limit=8.0, viscous_friction=5e-5),
    Effects(hill_force=3.0, hill_start=0.5, hill_length=2.0, aero_drag=0.5),
]


def _truck_and_series(k: int, eff: Effects) -> tuple[VehicleParams, Series]:
    """A drawn truck with a high breakaway torque and a log of it that stops often."""
    p0 = load_config().vehicle
    p = draw_truck(p0, np.random.default_rng(300 + k)).params
    p = p.replace(K_stiction=3.0 * p.K_coulomb)
    log = plant_log(p, eff, seed=k, n=1500, noise_i=0.0)
    c = log.columns
    return p, Series(t=c["t"], inp=c["u"], v=c["v"], i=None, x=None)


def _same_run(a: prediction.VoltagePrediction, b: prediction.VoltagePrediction) -> bool:
    return all(np.array_equal(x, y) for x, y in ((a.v, b.v), (a.v_true, b.v_true), (a.x, b.x)))


def test_the_kernel_is_there() -> None:
    """Without the kernel no run has a band: the tests below would hold trivially."""
    assert ckernel.available(), f"{ckernel.LIBRARY} missing: run `make firmware`"


def test_a_band_holds_from_its_stuck_end_up_to_but_not_its_moved_end() -> None:
    band = prediction.StictionBand(stuck=1.0, moved=2.0, kappa=1.0, J_S=1.0)
    assert band.holds(1.0) and band.holds(np.nextafter(2.0, 0.0))
    assert not band.holds(np.nextafter(1.0, 0.0)) and not band.holds(2.0)
    assert not prediction.StictionBand(-np.inf, np.inf, 1.0, 1.0).holds(float("nan"))


def test_the_bands_ends_are_exact(monkeypatch: pytest.MonkeyPatch) -> None:
    """The run itself at thresholds set directly: the same run at the band's stuck end and
    just below its moved end, in every case.  Just past either end a decision goes the
    other way; that changes the run in some cases, not all (a drive that breaks away
    against a larger Coulomb friction stops at once, as a stuck one: the band is
    conservative), so a difference is required in at least one case per end."""
    seen: list[tuple[freerun.Kinetics, freerun.Timeline, int, float, float]] = []
    run = fastsim.run

    def kept(kin: freerun.Kinetics, tl: freerun.Timeline, n: int, w0: float, lag: float,
             **kw: object) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
        seen.append((kin, tl, n, w0, lag))
        return run(kin, tl, n, w0, lag, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(fastsim, "run", kept)
    differs = {"below stuck": 0, "at moved": 0}
    for k, eff in enumerate(BANDED):
        p, s = _truck_and_series(k, eff)
        band = fastsim.predict(p, eff, s).stiction
        assert band is not None
        kin, tl, n, w0, lag = seen[-1]
        ref = freerun.run(kin, tl, n, w0, lag)

        def same(sigma: float) -> bool:
            out = freerun.run(dataclasses.replace(kin, sigma=sigma), tl, n, w0, lag)  # noqa: B023
            return all(np.array_equal(a, b) for a, b in zip(out, ref, strict=True))  # noqa: B023

        assert np.isfinite(band.stuck) or np.isfinite(band.moved), "never stopped"
        if np.isfinite(band.stuck):
            assert same(band.stuck), (k, band)
            differs["below stuck"] += not same(float(np.nextafter(band.stuck, -np.inf)))
        if np.isfinite(band.moved):
            assert same(float(np.nextafter(band.moved, -np.inf))), (k, band)
            differs["at moved"] += not same(band.moved)
    assert all(differs.values()), differs


@pytest.mark.parametrize("k", range(len(BANDED)))
def test_every_stiction_torque_in_the_band_gives_the_same_run(k: int) -> None:
    """Swept over torques from Coulomb to 20x it: each one the band holds gives the run
    bit for bit; the band is neither everything (torques outside it change the run) nor
    the run's own torque alone."""
    eff = BANDED[k]
    p, s = _truck_and_series(k, eff)
    ref = fastsim.predict(p, eff, s)
    band = ref.stiction
    assert band is not None and band.holds(p.K_stiction)
    inside = outside_changed = 0
    for ks in np.geomspace(p.K_coulomb, 20.0 * p.K_coulomb, 60):
        run = fastsim.predict(p.replace(K_stiction=float(ks)), eff, s)
        if band.holds(float(ks)):
            assert _same_run(run, ref), f"K_stiction {ks:.4g} in the band changed the run"
            inside += ks != p.K_stiction
        else:
            outside_changed += not _same_run(run, ref)
    assert inside > 0, "the band holds no other torque"
    assert outside_changed > 0, "no torque outside the band changes the run"


def test_a_run_that_never_stops_holds_every_stiction_torque() -> None:
    p, _ = _truck_and_series(0, Effects())
    t = np.linspace(0.0, 3.0, 301)
    u = np.full_like(t, 0.6 * p.V_batt)
    v = np.full_like(t, 1.0)
    s = Series(t=t, inp=u, v=v, i=None, x=None)
    band = fastsim.predict(p, Effects(), s).stiction
    assert band is not None
    assert band.stuck == -np.inf and band.moved == np.inf


def test_no_band_where_the_threshold_varies() -> None:
    """A Stribeck friction, a battery sag (per-command scale) or backlash: not known."""
    for eff in (
        Effects(stribeck=0.01, stribeck_speed=0.1),
        Effects(battery_sag=0.2),
        Effects(backlash=0.3, rotor_inertia_fraction=0.3),
        Effects(resistance_drift=1.2, winding_time_constant=15.0),
    ):
        p, s = _truck_and_series(1, eff)
        assert fastsim.predict(p, eff, s).stiction is None, eff


@pytest.mark.parametrize("k", [0, 2, 3])
def test_the_stiction_scan_finds_what_a_full_scan_finds_with_fewer_runs(
    k: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    eff = BANDED[k]
    p, s = _truck_and_series(k, eff)
    data = [s.slice(lo, lo + 300) for lo in range(0, 1200, 300)]
    w = voltage.weights_for(data)
    grid = voltage.stiction_grid(p, s)
    runs = {"n": 0}
    predict = voltage.predict

    def counted(*a: object) -> prediction.VoltagePrediction:
        runs["n"] += 1
        return predict(*a)  # type: ignore[arg-type]

    monkeypatch.setattr(voltage, "predict", counted)
    start = p.replace(K_stiction=p.K_coulomb)
    banded = voltage.scan_stiction(start, eff, grid, data, w)
    with_band = runs["n"]
    runs["n"] = 0
    monkeypatch.setattr(prediction.StictionBand, "holds", lambda self, ks: False)
    full = voltage.scan_stiction(start, eff, grid, data, w)
    assert banded[0] == full[0] and banded[1] == full[1]
    assert with_band < runs["n"], (with_band, runs["n"])


def test_the_first_order_filter_is_scipys_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    for trial in range(300):
        rows, cols = int(rng.integers(0, 300)), int(rng.integers(1, 6))
        x = rng.normal(size=(rows, cols)) * 10.0 ** rng.uniform(-6, 6, size=cols)
        if trial % 4 == 0:
            x = np.sign(x)  # the sign and indicator columns terrain filters
        a = float(np.exp(-rng.uniform(1e-4, 3.0)))
        ref = np.asarray(lfilter([0.0, 1.0 - a], [1.0, -a], x, axis=0))
        got = ckernel.first_order(x, 1.0 - a, -a)
        assert got is not None and got.shape == ref.shape
        assert np.array_equal(got.view(np.int64), ref.view(np.int64)), trial
    with pytest.raises(ValueError, match="2-D"):
        ckernel.first_order(np.zeros(3), 0.5, -0.5)


def test_the_electrical_correction_in_floats_is_the_array_forms() -> None:
    p0 = load_config().vehicle
    rng = np.random.default_rng(11)
    for _ in range(300):
        p = dataclasses.replace(
            draw_truck(p0, rng).params,
            L_m=p0.L_m * float(10.0 ** rng.uniform(-1.5, 1.5)),
            R_m=p0.R_m * float(10.0 ** rng.uniform(-1, 1)),
        )
        visc = float(rng.choice([0.0, 1e-6, 5e-5, 1e-3]))
        k, lag = fastsim.electrical_correction(p, visc)
        ka, laga = fastsim.electrical_correction(p, visc, np.array([p.R_m]))
        assert isinstance(k, float) and isinstance(lag, float)
        assert k == float(np.asarray(ka)[0]) and lag == float(np.asarray(laga)[0])
