"""The MPC's compiled cycle (truckd/control/ccycle.py, built by ``make firmware``) and its
Python path give the same commands, plans and iteration counts; the Python path is chosen,
and named, when the library is missing or does not fit the QP."""

from __future__ import annotations

import dataclasses
import gc
import random
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from truckd.config.truck import load_config
from truckd.control import ccycle
from truckd.control import mpc as mpc_module
from truckd.control.config import ControlConfig
from truckd.control.mpc import MpcSolver
from truckd.control.platoon import plan_of_array
from truckd.control.qp import ControlModel, QpInputs
from truckd.runtime.platoon_link import cycle_plan
from truckd.runtime.replay import cycle_from_params
from truckd.runtime.rxlog import read_rx_log

DATA = Path(__file__).parent / "data" / "replay"

needs_library = pytest.mark.skipif(
    ccycle.library()[0] is None, reason="compiled MPC cycle not built (make firmware)"
)


@pytest.fixture(autouse=True)
def garbage_solvers_give_theirs_back() -> None:
    """Solvers earlier tests left as garbage give their instances back (the cycle freezes
    the garbage collector's generations, so they are collected only once unfrozen); live
    ones, such as another test module's shared solver, keep theirs: a test that took an
    instance from a live solver would make two solvers share one workspace."""
    gc.unfreeze()
    gc.collect()


def _free_instances() -> int:
    lib, _ = ccycle.library()
    assert lib is not None
    return int(lib.truckd_mpc_instances()) - len(ccycle._held)


def _replay(compiled: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[list[Any], str]:
    """The recorded replay's cycles stepped again with the compiled or the Python path."""
    t0, params, cycles = read_rx_log(DATA / "run.rx.jsonl")
    init = MpcSolver.__init__

    def chosen(self: MpcSolver, model: ControlModel, cfg: ControlConfig, **_: bool) -> None:
        init(self, model, cfg, compiled=compiled)

    with monkeypatch.context() as m:
        m.setattr(mpc_module.MpcSolver, "__init__", chosen)
        cyc = cycle_from_params(params, t0, str(DATA / "run.rx.jsonl"))
    results = []
    inner = cyc.controller.mpc.solve

    def recording(mode: str, inp: QpInputs, warm: bool = True) -> Any:
        res = inner(mode, inp, warm)
        results.append(res)
        return res

    cyc.controller.mpc.solve = recording  # type: ignore[method-assign]
    outs = [cyc.step(inp) for inp in cycles]
    volts = [o.command.voltage for o in outs]
    return [volts, results], cyc.controller.mpc.backend


@needs_library
def test_compiled_and_python_paths_give_the_same_commands_on_the_recorded_replay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    (u_c, res_c), backend_c = _replay(True, monkeypatch)
    (u_p, res_p), backend_p = _replay(False, monkeypatch)
    assert backend_c == "compiled"
    assert backend_p.startswith("python (")
    assert len(u_c) == len(u_p) >= 250 and max(map(abs, u_p)) > 1.0  # it drove
    assert np.max(np.abs(np.array(u_c) - np.array(u_p))) <= 1e-9
    solved = [(a, b) for a, b in zip(res_c, res_p, strict=True) if b.ok]
    assert len(solved) == len(res_p) >= 250
    for a, b in solved:  # the same solves: status, iterations, the whole plan
        assert (a.ok, a.status, a.iterations) == (b.ok, b.status, b.iterations)
        assert a.u is not None and b.u is not None and a.v is not None and b.v is not None
        assert np.max(np.abs(a.u - b.u)) <= 1e-9 and np.max(np.abs(a.v - b.v)) <= 1e-9


def _drawn(seed: int) -> ControlModel:
    """A truck from a wide range: motor constant 0.5-3x, mass and inertia 0.5-5x, winding
    resistance 0.5-2x the shipped one's."""
    p = load_config().vehicle
    rng = random.Random(seed)
    fk, fm, fr = rng.uniform(0.5, 3.0), rng.uniform(0.5, 5.0), rng.uniform(0.5, 2.0)
    return ControlModel(
        dataclasses.replace(
            p, K_v=p.K_v * fk, K_T=p.K_T * fk, J_S=p.J_S * fm, m=p.m * fm, R_m=p.R_m * fr
        )
    )


def _sequence(cfg: ControlConfig, seed: int, n: int) -> list[tuple[str, QpInputs]]:
    """Inputs of a drive: a lead speeding up and braking, the gap and speed drifting,
    some cycles cruising without a lead, one with a lead forecast that varies."""
    rng = np.random.default_rng(seed)
    seq = []
    v, gap, u_prev = 0.5, 1.0, 0.0
    for k in range(n):
        v_lead = max(0.0, 1.0 + 0.8 * np.sin(k / 15.0))
        v = max(0.0, v + rng.normal(0.0, 0.03))
        gap = max(0.05, gap + (v_lead - v) * cfg.period)
        lead = k % 40 < 30
        forecast = [v_lead] * cfg.horizon if k % 7 else list(rng.uniform(0, 2, cfg.horizon))
        inp = QpInputs(
            x0=[rng.uniform(-0.5, 0.5), v, gap],
            u_prev=u_prev,
            v_lead=forecast,
            lead=lead,
            v_ref=1.2,
            v_cap=cfg.v_max,
            u_lo=-cfg.u_max,
            u_hi=cfg.u_max,
        )
        seq.append(("follow" if lead else "cruise", inp))
        u_prev = float(np.clip(u_prev + rng.normal(0.0, 0.2), -cfg.u_max, cfg.u_max))
    return seq


@needs_library
@pytest.mark.parametrize("seed", range(4))
def test_compiled_and_python_solvers_agree_for_drawn_trucks(seed: int) -> None:
    """Trucks drawn from a wide range: each runs compiled (or names why not) and solves
    every QP of a drive as the Python path does, warm starts and restarts included."""
    cfg = dataclasses.replace(load_config().control, time_budget_s=float("inf"))
    model = _drawn(seed)
    compiled = MpcSolver(model, cfg)
    python = MpcSolver(model, cfg, compiled=False)
    assert compiled.backend == "compiled", compiled.backend
    for k, (mode, inp) in enumerate(_sequence(cfg, seed, 150)):
        if k == 60:
            compiled.restart()
            python.restart()
        warm = k % 50 != 25
        a, b = compiled.solve(mode, inp, warm), python.solve(mode, inp, warm)
        assert (a.ok, a.status, a.iterations) == (b.ok, b.status, b.iterations), k
        assert abs(a.u0 - b.u0) <= 1e-9 or (np.isnan(a.u0) and np.isnan(b.u0)), k
        assert compiled.has_warm_start == python.has_warm_start
    la, lb = compiled.last_solution, python.last_solution
    assert la is not None and lb is not None and np.max(np.abs(la - lb)) <= 1e-9


@needs_library
def test_the_admm_settings_reach_the_compiled_solver(monkeypatch: pytest.MonkeyPatch) -> None:
    """Relaxation and rho adaptation other than the generated solver was made with (as
    ``benchmarks/mpc_settings.py`` tries them): the compiled path takes them from
    ``osqp_settings`` at start-up and solves as the Python path does."""
    cfg = dataclasses.replace(load_config().control, time_budget_s=float("inf"))
    model = _drawn(1)
    seq = _sequence(cfg, 1, 120)
    shipped_iters = [MpcSolver(model, cfg).solve(m, i).iterations for m, i in seq[:1]]
    shipped = mpc_module.osqp_settings
    other = {"rho": 0.03, "alpha": 1.8, "adaptive_rho_interval": 25, "adaptive_rho_tolerance": 5.0}
    monkeypatch.setattr(mpc_module, "osqp_settings", lambda c: {**shipped(c), **other})
    compiled, python = MpcSolver(model, cfg), MpcSolver(model, cfg, compiled=False)
    assert compiled.backend == "compiled", compiled.backend
    iters = []
    for k, (mode, inp) in enumerate(seq):
        a, b = compiled.solve(mode, inp), python.solve(mode, inp)
        assert (a.ok, a.status, a.iterations) == (b.ok, b.status, b.iterations), k
        assert abs(a.u0 - b.u0) <= 1e-9 or (np.isnan(a.u0) and np.isnan(b.u0)), k
        iters.append(a.iterations)
    assert iters[:1] != shipped_iters  # the settings changed the solves


@needs_library
def test_non_finite_inputs_are_refused_before_the_compiled_cycle() -> None:
    cfg = load_config().control.in_simulated_time()  # no wall-clock budget
    s = MpcSolver(_drawn(7), cfg)
    assert s.backend == "compiled"
    _, inp = _sequence(cfg, 7, 1)[0]
    bad = dataclasses.replace(inp, x0=[0.0, float("nan"), 1.0])
    res = s.solve("follow", bad)
    assert not res.ok and res.status == "non-finite-input" and np.isnan(res.u0)
    assert s.solve("follow", inp).ok  # and the next good cycle solves


@pytest.mark.usefixtures("no_library")
def test_without_the_library_the_python_path_runs_and_says_why() -> None:
    cfg = load_config().control.in_simulated_time()  # no wall-clock budget
    s = MpcSolver(_drawn(1), cfg)
    assert s.backend == "python (libtruckd_mpc.so not built (make firmware))"
    _, inp = _sequence(cfg, 1, 1)[0]
    assert s.solve("follow", inp).ok


@needs_library
def test_a_qp_of_another_shape_runs_the_python_path_and_says_why() -> None:
    cfg = dataclasses.replace(load_config().control, horizon=20)
    s = MpcSolver(_drawn(2), cfg)
    assert s.backend.startswith("python (generated for a QP of 10 variables and 85 rows")
    sparse = MpcSolver(_drawn(2), dataclasses.replace(cfg, move_blocks=0))
    assert sparse.backend.startswith("python (the sparse QP")


@needs_library
def test_solvers_beyond_the_instances_run_python_until_one_is_released() -> None:
    cfg = load_config().control
    lib, _ = ccycle.library()
    assert lib is not None
    count = int(lib.truckd_mpc_instances())
    free = _free_instances()
    assert free >= 1
    held = [MpcSolver(_drawn(3), cfg) for _ in range(free)]
    assert all(s.backend == "compiled" for s in held)
    assert len({s._cc.instance for s in held if s._cc is not None}) == free
    extra = MpcSolver(_drawn(3), cfg)
    assert extra.backend.startswith(f"python (all {count} compiled instances held")
    del held[0]
    gc.collect()
    assert MpcSolver(_drawn(3), cfg).backend == "compiled"


@needs_library
def test_an_instance_used_before_gives_the_same_solves_bit_for_bit() -> None:
    """A solver on an instance another truck used gives what a fresh one gave (a
    simulation run twice in one process is deterministic)."""
    cfg = dataclasses.replace(load_config().control, time_budget_s=float("inf"))
    seq = _sequence(cfg, 5, 60)

    def run(seed: int) -> tuple[int, list[float]]:
        s = MpcSolver(_drawn(seed), cfg)
        assert s._cc is not None
        out = [s.solve(mode, inp).u0 for mode, inp in seq]
        instance = s._cc.instance
        del s
        gc.collect()
        return instance, out

    first, other, again = run(5), run(6), run(5)
    assert first[0] == other[0] == again[0]  # the same instance, reused
    assert first[1] == again[1] and first[1] != other[1]


def _bits(x: Any) -> list[int]:
    """Each float's bit pattern (tells -0.0 from 0.0; a NaN equals the same NaN)."""
    return np.asarray(x, dtype=np.float64).view(np.int64).tolist()


@needs_library
def test_the_compiled_plan_is_plan_of_array_of_the_speeds_on_the_recorded_replay() -> None:
    """Every cycle of the replay: the plan the compiled cycle made (speeds clipped,
    accelerations) is, bit for bit, the plan made from the predicted speeds in Python."""
    t0, params, rx = read_rx_log(DATA / "run.rx.jsonl")
    cycles = list(rx)
    cyc = cycle_from_params(params, t0, str(DATA / "run.rx.jsonl"))
    compiled = 0
    for k, inp in enumerate(cycles):
        out = cyc.step(inp)
        speeds = cyc.plan_speed_array(out)
        plan = cycle_plan(cyc, out, 0.5 * k, "t1")
        if speeds is None:
            assert plan is None or plan.v == (0.0,) * len(plan.v)  # none, or held at rest
            continue
        compiled += cyc.compiled_plan(speeds) is not None
        ref = plan_of_array(0.5 * k, out.seq, cyc.period, speeds, "t1")
        assert plan is not None and _bits(plan.v) == _bits(ref.v), k
        assert _bits(plan.a) == _bits(ref.a) and plan.as_dict() == ref.as_dict(), k
    assert compiled > 0.9 * len(cycles)


@needs_library
def test_the_compiled_plan_clips_and_differences_any_speeds_as_python_does() -> None:
    """Speeds no solve gives (negative, -0.0, NaN, infinite, huge) put in the bound speeds:
    the compiled plan of them is plan_of_array's, bit for bit."""
    cfg = load_config().control
    s = MpcSolver(_drawn(4), cfg)
    cc = s.compiled_cycle
    assert cc is not None
    rng = np.random.default_rng(9)
    specials = np.array([-1.0, -0.0, 0.0, np.nan, np.inf, -np.inf, 1e308, -1e-300, 5e-324])
    for trial in range(200):
        v = rng.normal(0.5, 1.0, cc.v.size)
        if trial % 2:
            idx = rng.integers(0, v.size, 6)
            v[idx] = rng.choice(specials, 6)
        cc.v[:] = v
        cc.plan_of_v()
        with np.errstate(over="ignore", invalid="ignore"):  # inf - inf, 1e308 / 0.01
            ref = plan_of_array(0.0, 0, cfg.period, v)
        n = cc.v.size
        assert _bits(cc.plan[:n]) == _bits(ref.v), trial
        assert _bits(cc.plan[n:]) == _bits(ref.a), trial
