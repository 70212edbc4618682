"""Closed-loop scenarios through the simulated firmware and the real protocol: the pass
criteria of each scenario (no collision, gap error, limits), and ``truckd sim`` end to end."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from truckd.cli.main import main
from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.sim.closed_loop import SimSetup, Trace, run_scenario
from truckd.sim.scenarios import SCENARIO_NAMES, SpeedProfile, World, make_scenario

CONTRACT_KEYS = {
    "scenario",
    "duration_s",
    "cycles",
    "collision",
    "min_gap_m",
    "gap_error_rms_m",
    "max_abs_voltage_v",
    "solve_us_p50",
    "solve_us_p99",
    "step_us_p99",
    "solver_failures",
    "deadline_misses",
}


def shipped_setup() -> SimSetup:
    """The shipped configuration, as ``truckd sim`` runs it (simulated time: the solver is
    judged by what it did, so the runs do not depend on the machine's load)."""
    tc = load_config()
    return SimSetup.from_config(tc)


@pytest.fixture(scope="module")
def runs() -> dict[str, tuple[dict[str, Any], Trace]]:
    tc = load_config()
    setup = shipped_setup()
    return {
        n: run_scenario(make_scenario(n, tc.vehicle, tc.control), setup) for n in SCENARIO_NAMES
    }


@pytest.mark.parametrize("name", SCENARIO_NAMES)
def test_no_collision_gap_above_minimum_voltage_within_limits(
    runs: dict[str, tuple[dict[str, Any], Trace]], name: str
) -> None:
    cfg = load_config().control
    m, tr = runs[name]
    assert set(m) >= CONTRACT_KEYS
    assert not m["collision"]
    gaps = np.array(tr.gap)
    if name != "cruise":
        assert np.nanmin(gaps) >= cfg.d_min
    u = np.array(tr.u)
    assert np.all(np.isfinite(u))
    assert np.max(np.abs(u)) <= cfg.u_max + 1e-9
    # The rate limit holds on every step.
    assert np.max(np.abs(np.diff(u))) <= cfg.du_max * cfg.period + 1e-9


@pytest.mark.parametrize(
    "scale", [{"J_S": 5.0}, {"K_T": 0.3, "K_v": 0.3}], ids=["inertia x5", "motor constant x0.3"]
)
def test_stop_and_go_on_trucks_far_from_the_default_never_stops_on_the_solver(
    scale: dict[str, float],
) -> None:
    """Trucks far from the default, modelled right: creeping up to a stopped lead, some
    QPs take OSQP 600 iterations (measured).  With the former limit of 400 they failed ten
    cycles running, and the supervisor stopped the truck in a normal manoeuvre."""
    tc = load_config()
    p = tc.vehicle.replace(**{k: getattr(tc.vehicle, k) * f for k, f in scale.items()})
    setup = dataclasses.replace(shipped_setup(), plant_params=p, model=ControlModel(p))
    m, _tr = run_scenario(make_scenario("stop-and-go", p, tc.control), setup)
    assert not m["collision"]
    assert m["solver_failures"] <= 2  # isolated ones are covered by the held plan
    assert m["mode_time_s"]["SAFE_STOP"] == 0.0 and m["mode_time_s"]["DEGRADED"] == 0.0


def test_follow_settles_within_2cm_of_the_reference_gap(
    runs: dict[str, tuple[dict[str, Any], Trace]],
) -> None:
    cfg = load_config().control
    _, tr = runs["follow"]
    t = np.array(tr.t)
    last = t >= t[-1] - 3.0
    err = np.array(tr.gap)[last] - (cfg.d_0 + cfg.time_headway * np.array(tr.v)[last])
    assert np.max(np.abs(err)) <= 0.02
    # And the truck really follows at the lead's speed.
    assert np.mean(np.array(tr.v)[last]) == pytest.approx(np.array(tr.v_lead)[-1], abs=0.01)


def test_cruise_holds_the_set_speed(runs: dict[str, tuple[dict[str, Any], Trace]]) -> None:
    m, _ = runs["cruise"]
    assert m["final_speed_m_s"] == pytest.approx(load_config().control.v_set, abs=0.02)
    assert m["min_gap_m"] is None and m["gap_error_rms_m"] is None


def test_lead_brake_stops_behind_the_lead(runs: dict[str, tuple[dict[str, Any], Trace]]) -> None:
    m, tr = runs["lead-brake"]
    assert tr.v[-1] == pytest.approx(0.0, abs=0.02)
    assert m["min_gap_m"] > load_config().control.d_min


def test_lead_lost_then_cruise(runs: dict[str, tuple[dict[str, Any], Trace]]) -> None:
    _, tr = runs["lead-lost"]
    assert tr.mode[-1] == "cruise"
    assert np.mean(tr.v[-100:]) == pytest.approx(load_config().control.v_set, abs=0.03)
    # During the short sensor dropout (6.0-6.2 s) the truck kept following.
    t = np.array(tr.t)
    during = (t >= 6.0) & (t < 6.2)
    assert all(m == "follow" for m, d in zip(tr.mode, during, strict=True) if d)


def test_cut_in_opens_the_gap_again(runs: dict[str, tuple[dict[str, Any], Trace]]) -> None:
    cfg = load_config().control
    _, tr = runs["cut-in"]
    t = np.array(tr.t)
    gap = np.array(tr.gap)
    k = int(np.argmax(t >= 8.0))
    assert gap[k + 1] < 0.6 * gap[k - 1]  # the gap halved
    err_end = gap[-1] - (cfg.d_0 + cfg.time_headway * tr.v[-1])
    assert abs(err_end) < 0.02


def test_speed_profile_distance_is_the_integral_of_speed() -> None:
    prof = SpeedProfile((0.0, 1.0, 3.0, 4.0), (1.0, 1.0, 0.0, 2.0))
    ts = np.linspace(0.0, 6.0, 60001)
    vs = np.array([prof.speed(t) for t in ts])
    numeric = np.concatenate([[0.0], np.cumsum(0.5 * (vs[1:] + vs[:-1]) * np.diff(ts))])
    for k in (0, 5000, 15000, 25000, 35000, 60000):
        assert prof.distance(float(ts[k])) == pytest.approx(numeric[k], abs=1e-6)


def test_world_cut_in_halves_the_gap_once() -> None:
    cfg = load_config()
    sc = make_scenario("cut-in", cfg.vehicle, cfg.control)
    w = World(sc)
    assert sc.cut_in_time is not None
    before = w.gap(sc.cut_in_time - 0.01, 0.0)
    after = w.gap(sc.cut_in_time, 0.0)
    later = w.gap(sc.cut_in_time + 1.0, 0.0)
    assert before is not None and after is not None and later is not None
    v = sc.lead.speed(0.0) if sc.lead else math.nan
    assert after == pytest.approx(0.5 * (before + 0.01 * v), rel=1e-9)
    assert later == pytest.approx(after + v, rel=1e-9)


def test_unknown_scenario_is_rejected() -> None:
    cfg = load_config()
    with pytest.raises(ValueError, match="unknown scenario"):
        make_scenario("nope", cfg.vehicle, cfg.control)


def test_cli_sim_writes_contract_json_and_plot(tmp_path: Path) -> None:
    out, png = tmp_path / "sim.json", tmp_path / "sim.png"
    code = main(
        ["sim", "--scenario", "follow", "--duration", "3", "--json", str(out), "--plot", str(png)]
    )
    assert code == 0
    doc = json.loads(out.read_text())
    assert set(doc) >= CONTRACT_KEYS
    assert doc["scenario"] == "follow" and doc["cycles"] == 300
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_sim_all_writes_a_list_of_every_scenario(tmp_path: Path) -> None:
    out = tmp_path / "all.json"
    assert main(["sim", "--scenario", "all", "--duration", "0.5", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert isinstance(doc, list)
    assert [d["scenario"] for d in doc] == list(SCENARIO_NAMES)
    assert all(set(d) >= CONTRACT_KEYS and d["cycles"] == 50 for d in doc)


def test_cli_sim_collision_exits_1(monkeypatch: pytest.MonkeyPatch) -> None:
    import truckd.cli.sim as cli_sim

    real = cli_sim.run_scenario

    def crashed(*args: Any, **kwargs: Any) -> tuple[dict[str, Any], Trace]:
        m, tr = real(*args, **kwargs)
        return {**m, "collision": True}, tr

    monkeypatch.setattr(cli_sim, "run_scenario", crashed)
    assert main(["sim", "--scenario", "follow", "--duration", "0.2"]) == 1


def test_cli_sim_bad_duration_and_model_exit_2(tmp_path: Path) -> None:
    assert main(["sim", "--scenario", "follow", "--duration", "-1"]) == 2
    bad = tmp_path / "m.yaml"
    bad.write_text("vehicle: {R_m: 1}\n")
    assert main(["sim", "--scenario", "follow", "--model", str(bad)]) == 2


def test_model_file_with_the_plants_effect_beats_the_seed_model(tmp_path: Path) -> None:
    """Seed model against extended model through the CLI: the plant has a 50 ms input delay; the
    controller with the seed model oscillates, with the extended MODEL.yaml it does not."""
    import yaml

    from truckd.config.truck import default_config_path
    from truckd.model.effects import Effects
    from truckd.modelfile import ModelFile, write_model

    doc = yaml.safe_load(default_config_path().read_text())
    doc["plant"]["effects"]["input_delay"] = 0.05
    # The earlier, aggressive tuning (rate weight 0.3, own-speed filter 3 m/s^2): the
    # shipped smoother one keeps even the seed model stable at 50-100 ms delay.
    doc["control"]["r_du"] = 0.3
    doc["control"]["estimator"]["speed_accel_std"] = 3.0
    cfg_file = tmp_path / "truck.yaml"
    cfg_file.write_text(yaml.safe_dump(doc))
    model_file = tmp_path / "MODEL.yaml"
    write_model(model_file, ModelFile(load_config().vehicle, Effects(input_delay=0.05), "test"))
    rms = {}
    for name, extra in (("seed", []), ("extended", ["--model", str(model_file)])):
        out = tmp_path / f"{name}.json"
        args = ["sim", "--scenario", "follow", "--duration", "10", "--config", str(cfg_file)]
        assert main([*args, "--json", str(out), *extra]) == 0
        rms[name] = json.loads(out.read_text())["gap_error_rms_m"]
    assert rms["extended"] < 0.01
    assert rms["seed"] > 5 * rms["extended"]


def _segments(mask: np.ndarray) -> list[tuple[int, int]]:
    """Index ranges [start, end) where mask is True."""
    out, k = [], 0
    while k < len(mask):
        if mask[k]:
            j = k
            while j < len(mask) and mask[j]:
                j += 1
            out.append((k, j))
            k = j
        else:
            k += 1
    return out


HOLD_WITHIN_S = 3.0
"""The standstill hold starts at most this long after the lead has stopped (measured:
2.3 s after lead-brake's hardest stop from 1.6 m/s, 1.8 s in stop-and-go)."""
RESTART_WITHIN_S = 0.25
"""The truck moves (> moving_speed) at most this long after the lead starts to move
(measured: 0.17 s, the lead accelerating at 2 m/s^2; the lead-speed estimate must exceed
hold_release_speed for hold_release_cycles cycles, then the breakaway)."""


@pytest.mark.parametrize(("name", "stops"), [("lead-brake", 1), ("stop-and-go", 2)])
def test_standstill_hold_no_creep_then_prompt_restart(
    runs: dict[str, tuple[dict[str, Any], Trace]], name: str, stops: int
) -> None:
    """Behind a stopped lead the truck ends exactly at rest (the gap, i.e. its position,
    constant) in mode hold, with the gap within hold_gap_tol of d_0 and above d_min, until
    the lead goes; then it starts promptly; one hold per stop (no chatter)."""
    cfg = load_config().control
    _, tr = runs[name]
    t, gap, v = np.array(tr.t), np.array(tr.gap), np.array(tr.v)
    hold = np.array([m == "hold" for m in tr.mode])
    stopped = _segments(np.array(tr.v_lead) == 0.0)
    assert len(stopped) == stops
    assert len(_segments(hold)) == stops  # one hold per stop: no chatter
    for a, b in stopped:
        k = a + int(np.argmax(hold[a:b]))
        assert hold[k] and t[k] - t[a] <= HOLD_WITHIN_S
        assert np.all(hold[k:b])  # held for the remainder of the standstill
        # Entered at an estimated speed <= moving_speed: the truck coasts to rest on
        # friction within a few cycles, then does not move at all (no creep).
        r = k + int(np.argmax(v[k:b] == 0.0))
        assert v[r] == 0.0 and t[r] - t[k] <= 0.1
        assert np.all(v[r:b] == 0.0)
        assert np.ptp(gap[r:b]) == 0.0
        assert abs(gap[b - 1] - cfg.d_0) <= cfg.hold_gap_tol
        assert np.min(gap[a:b]) >= cfg.d_min
        assert np.all(np.array(tr.u)[k:b] == 0.0)
        if b < len(t):  # the lead goes again
            moving = np.nonzero(v[b:] > cfg.moving_speed)[0]
            assert moving.size and t[b + moving[0]] - t[b] <= RESTART_WITHIN_S
            assert not np.any(hold[b + moving[0] :][: int(1.0 / cfg.period)])
