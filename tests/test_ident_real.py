"""Logs as other people record them: single steps, pauses, several files, trucks far
from the configured one, physically impossible best fits.

Drawn trucks have 0.1x..10x the default motor constant and inertia (log-uniform),
logged at 50-200 Hz with jittered timing, dropped rows and coarse speed steps
(:func:`labkit.synth.draw_truck`); the seeds come from one fixed SeedSequence,
not picked per case.  The wide draw (every effect, many seeds) is in
benchmarks/diagnose_bench.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from labkit.synth import (
    draw_truck,
    drawn_log,
    plant_log,
    random_effect,
    scaled_effect,
    with_effect,
)

from truckd.cli.main import main
from truckd.errors import InputError
from truckd.ident.api import diagnose_log, identify_log
from truckd.ident.data import runs_from_logs
from truckd.ident.linear import feedforward_of
from truckd.logfile import Log, write_log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

SEEDS = [int(s) for s in np.random.SeedSequence(1010).generate_state(8)]

TOLERANCE: dict[str, tuple[float, float]] = {
    "load_force": (0.05, 0.2),  # N (absolute part scaled with the motor constant)
    "input_delay": (0.0, 0.004),  # s
    "dead_zone": (0.0, 0.3),  # V
    "sensor_lag": (0.10, 0.0),
}


def _step_log(p: VehicleParams, u0: float, u1: float, seed: int, hz: float = 100.0) -> Log:
    """One step u0 -> u1 at 1 s, 6 s long, speed noise, no current (a lab experiment)."""
    t = np.arange(int(6.0 * hz)) / hz
    u = np.where(t < 1.0, u0, u1)
    v0 = 0.0
    if u0 != 0.0:  # start in the steady state of the first level
        pre = simulate_open_loop(p, np.arange(500) * 0.01, np.full(500, u0))
        v0 = float(pre.v_true[-1])
    sim = simulate_open_loop(p, t, u, PlantConfig(noise_v=0.01, seed=seed), v0=v0)
    return Log({"t": t, "u": u, "v": sim.v}, f"step {u0}->{u1}")


@pytest.mark.parametrize("u0,u1", [(0.0, 4.0), (2.0, 5.0)])
def test_single_step_is_accepted_and_fitted(params: VehicleParams, u0: float, u1: float) -> None:
    """A step on a truck 3x off the configuration: the steady state and the time
    constant are recovered; between two levels (two steady states) also the motor
    constant.  From rest, kS and kV only show as the one steady state (u - kS)/kV."""
    true = params.replace(
        K_v=params.K_v * 3, K_T=params.K_T * 3, J_S=params.J_S * 2, K_coulomb=0.03
    )
    true = true.replace(K_stiction=0.04)
    m = identify_log(_step_log(true, u0, u1, SEEDS[0]), params).vehicle
    got, want = feedforward_of(m), feedforward_of(true)
    assert (u1 - got.kS) / got.kV == pytest.approx((u1 - want.kS) / want.kV, rel=0.02)
    assert got.kA / got.kV == pytest.approx(want.kA / want.kV, rel=0.1)
    if u0 != 0.0:
        assert got.kV == pytest.approx(want.kV, rel=0.05)


def test_single_step_validates(params: VehicleParams) -> None:
    fit = plant_log(params, Effects(), seed=SEEDS[1], n=3000, with_current=False)
    d = diagnose_log(fit, params, validate=_step_log(params, 0.0, 4.0, SEEDS[2]))
    assert d.baseline.fit_percent > 95.0
    assert d.effects == []


def _paused(p: VehicleParams, eff: Effects, pause: float) -> Log:
    """Two random-excitation runs of 25 s in one file, ``pause`` s apart on the clock."""
    a = plant_log(p, eff, seed=SEEDS[3], n=2500, with_current=False)
    b = plant_log(p, eff, seed=SEEDS[4], n=2500, with_current=False)
    t = np.concatenate([a["t"], b["t"] + a["t"][-1] + pause])
    cols = {k: np.concatenate([a[k], b[k]]) for k in ("u", "v")}
    return Log({"t": t, **cols}, "paused.csv")


def test_pause_splits_a_log_into_runs(params: VehicleParams) -> None:
    log = _paused(params, Effects(), pause=120.0)
    assert len(runs_from_logs([log])) == 2
    assert len(runs_from_logs([log], gap=200.0)) == 1
    d = diagnose_log(log, params)
    assert d.runs == 2
    # Each run simulated from its own start: the seed model fits both.
    assert d.baseline.fit_percent > 95.0
    assert d.effects == []
    assert not d.unexplained


def test_several_files_and_gap_on_the_command_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], params: VehicleParams
) -> None:
    log = _paused(params, Effects(), pause=120.0)
    write_log(tmp_path / "p.csv", log.columns)
    one = plant_log(params, Effects(), seed=SEEDS[5], n=1500, with_current=False)
    write_log(tmp_path / "a.csv", one.columns)
    model = tmp_path / "m.yaml"
    assert (
        main(["identify", str(tmp_path / "p.csv"), str(tmp_path / "a.csv"), "--out", str(model)])
        == 0
    )
    assert model.exists()
    capsys.readouterr()
    assert main(["identify", str(tmp_path / "a.csv"), "--gap", "-1", "--out", str(model)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--gap" in err[0]


def test_impossible_best_fit_is_not_accepted(params: VehicleParams) -> None:
    """A load larger than the truck's weight (m g = 34 N) fits best but is impossible:
    reported with the reason, never named as a cause."""
    weight = params.m * 9.81
    d = diagnose_log(
        plant_log(params, with_effect("load_force", 1.5 * weight), SEEDS[6], n=4000), params
    )
    assert "load_force" not in [f.name for f in d.effects]
    rejected = {r.name: r for r in d.rejected}
    assert "load_force" in rejected
    assert "weight" in rejected["load_force"].reason
    assert abs(rejected["load_force"].params["load_force"]) > weight


CASES = [
    ("load_force", 0),
    ("input_delay", 1),
    ("dead_zone", 2),
    ("sensor_lag", 3),
    ("none", 4),
    ("none", 5),
]


@pytest.mark.parametrize("name,k", CASES)
def test_hidden_effect_on_a_drawn_truck(params: VehicleParams, name: str, k: int) -> None:
    """A truck 0.1x..10x off the configuration, logged imperfectly: the hidden effect is
    named and recovered; a clean log: nothing named and the seed model fits."""
    rng = np.random.default_rng(np.random.SeedSequence(2026).spawn(8)[k])
    truck = draw_truck(params, rng)
    if name == "none":
        eff, value = Effects(), 0.0
    else:
        value = scaled_effect(name, random_effect(name, rng), truck.k_scale)
        eff = with_effect(name, value)
    d = diagnose_log(drawn_log(truck, eff, int(rng.integers(1 << 30))), params)
    names = [f.name for f in d.effects]
    what = f"truck k={truck.k_scale:.3g} J={truck.j_scale:.3g} {truck.rate_hz:.0f} Hz"
    assert d.vehicle is not None
    # The seed parameters are found although the configuration is far off.
    assert d.vehicle.K_v == pytest.approx(truck.params.K_v, rel=0.1), what
    if name == "none":
        assert names == [], f"{what}: clean log, named {names}"
        assert d.baseline.fit_percent > 90.0, what
        return
    assert names == [name], f"{what}: hidden {name}={value:.4g}, named {names}"
    found = next(iter(d.effects[0].params.values()))
    rel, ab = TOLERANCE[name]
    if name == "load_force":
        ab *= truck.k_scale
    assert abs(found - value) <= max(rel * abs(value), ab), f"{what}: {found:.4g} vs {value:.4g}"
    assert d.extended.fit_percent > d.baseline.fit_percent


def test_log_of_one_sample_per_run_is_refused(params: VehicleParams) -> None:
    t = np.cumsum(np.tile([0.01, 0.01, 0.01, 0.01, 5.0], 20))  # a pause every 5 samples
    with pytest.raises(InputError, match="no stretch"):
        diagnose_log(Log({"t": t, "u": np.sin(t), "v": np.sin(t)}, "sparse.csv"), params)
