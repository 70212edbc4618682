"""The controller's numerics around the MPC in one compiled call (truckd/control/cnumerics.py,
truckd/control/kernel/cycle_numerics.c) give the commands of its Python path (the
reference and the fallback), on the recorded replay and on drives with starts from rest,
failed solves and non-finite inputs; the command is finite and within limits on both paths
whatever arrives; a model the compiled numerics do not serve runs Python and says why."""

from __future__ import annotations

import dataclasses
import gc
import math
import random
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from truckd.config.truck import load_config
from truckd.control import ccycle
from truckd.control import mpc as mpc_module
from truckd.control.cnumerics import CONSTANTS, constants
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.estimator import Estimate
from truckd.control.mpc import MpcSolver
from truckd.control.output import ControlOutput
from truckd.control.qp import ControlModel
from truckd.model.effects import Effects
from truckd.runtime.replay import cycle_from_params
from truckd.runtime.rxlog import read_rx_log

DATA = Path(__file__).parent / "data" / "replay"
TICKS = load_config().ticks_per_rev

needs_library = pytest.mark.skipif(
    ccycle.library()[0] is None, reason="compiled MPC cycle not built (make firmware)"
)


@pytest.fixture(autouse=True)
def garbage_solvers_give_theirs_back() -> None:
    """Solvers earlier tests left as garbage give their compiled instances back."""
    gc.unfreeze()
    gc.collect()


def _counted(ctrl: Controller) -> list[int]:
    """How many cycles ran the compiled numerics (a counter around its call)."""
    num = ctrl._numerics
    assert num is not None
    calls = [0]
    run, run_cycle = num.run, num.run_cycle

    def counting(*args: Any) -> Any:
        calls[0] += 1
        return run(*args)

    def counting_cycle(*args: Any) -> Any:
        status, est = run_cycle(*args)
        calls[0] += status != ccycle.ESTIMATED  # it went on to the solve
        return status, est

    num.run = counting  # type: ignore[method-assign]
    num.run_cycle = counting_cycle  # type: ignore[method-assign]
    return calls


def _same(a: ControlOutput, b: ControlOutput, where: object) -> None:
    """The same command (1e-9 V) and the same decisions."""
    assert math.isfinite(a.u) and math.isfinite(b.u), where
    assert abs(a.u - b.u) <= 1e-9, where
    # (a non-finite disturbance estimate or resistance makes the feedforward non-finite on
    # both: the command then comes from the fallback)
    f, g = a.u_ff, b.u_ff
    assert f == g or abs(f - g) <= 1e-9 or (math.isnan(f) and math.isnan(g)), where
    assert (a.mode, a.fallback_reason, a.solver_status, a.solve_iterations) == (
        b.mode, b.fallback_reason, b.solver_status, b.solve_iterations,
    ), where  # fmt: skip


def _python_controller(model: ControlModel, cfg: ControlConfig) -> Controller:
    """A controller whose MPC and numerics run the Python path."""
    init = MpcSolver.__init__

    def python(self: MpcSolver, m: ControlModel, c: ControlConfig, **_: bool) -> None:
        init(self, m, c, compiled=False)

    mp = pytest.MonkeyPatch()
    mp.setattr(mpc_module.MpcSolver, "__init__", python)
    try:
        return Controller(model, cfg, TICKS)
    finally:
        mp.undo()


@needs_library
def test_compiled_numerics_give_the_python_commands_on_the_recorded_replay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    t0, params, cycles = read_rx_log(DATA / "run.rx.jsonl")
    cycles = list(cycles)
    compiled = cycle_from_params(params, t0, "compiled")
    calls = _counted(compiled.controller)
    init = MpcSolver.__init__

    def python(self: MpcSolver, m: ControlModel, c: ControlConfig, **_: bool) -> None:
        init(self, m, c, compiled=False)

    with monkeypatch.context() as mp:
        mp.setattr(mpc_module.MpcSolver, "__init__", python)
        reference = cycle_from_params(params, t0, "python")
    assert compiled.controller.backend.startswith("compiled (")
    assert reference.controller.backend.startswith("MPC python (")
    outs = [(compiled.step(inp), reference.step(inp)) for inp in cycles]
    assert calls[0] >= 250  # the compiled numerics computed (nearly) every command
    u_c = np.array([a.command.voltage for a, _ in outs])
    u_p = np.array([b.command.voltage for _, b in outs])
    assert len(u_c) >= 250 and np.max(np.abs(u_p)) > 1.0  # it drove
    assert np.max(np.abs(u_c - u_p)) <= 1e-9
    for k, (a, b) in enumerate(outs):
        assert a.control is not None and b.control is not None
        _same(a.control, b.control, k)


def _estimate(v: float, gap: float, v_lead: float, x: float, lead: bool = True) -> Estimate:
    return Estimate(
        v=v, speed_valid=True, gap=gap, v_lead=v_lead, lead_valid=lead,
        lead_status="tracking" if lead else "none", gap_std=0.01, outliers=0, reinits=0,
        encoder_samples=10, range_samples=10, x=x,
    )  # fmt: skip


def _drawn(seed: int) -> ControlModel:
    """A truck other than the configured one (motor constant, mass, friction, resistance):
    the compiled numerics get its constants, not the configured truck's."""
    p = load_config().vehicle
    rng = random.Random(seed)
    fk, fm, ff, fr = (rng.uniform(0.6, 2.0) for _ in range(4))
    return ControlModel(
        dataclasses.replace(
            p, K_v=p.K_v * fk, K_T=p.K_T * fk, m=p.m * fm, J_S=p.J_S * fm,
            K_coulomb=p.K_coulomb * ff, K_stiction=p.K_stiction * ff, R_m=p.R_m * fr,
        )
    )  # fmt: skip


def _drive(
    ctrl: Controller, seed: int, n: int, poke: Callable[[Controller, int], None]
) -> list[ControlOutput]:
    """A drive on estimates fed to the controller: a lead that stops, waits and goes (the
    truck at rest, starts from rest), the truck's speed following the commands roughly,
    headway changes, a forecast now and then; ``poke`` changes the controller before
    cycle k (failures, non-finite values)."""
    rng = np.random.default_rng(seed)
    v, gap, x, out = 0.0, 1.2, 0.0, []
    for k in range(n):
        v_lead = max(0.0, 1.2 * math.sin(k / 25.0))
        poke(ctrl, k)
        forecast = None if k % 9 else [v_lead + 0.01 * j for j in range(ctrl.forecast_steps)]
        headway = None if k % 5 else 0.3 + 0.01 * (k % 30)
        o = ctrl.control(_estimate(v, gap, v_lead, x, lead=k % 70 < 60), forecast, headway)
        out.append(o)
        v = max(0.0, v + 0.02 * (o.u - o.u_ff) + rng.normal(0.0, 0.01)) if o.u > 0.3 else 0.0
        gap = max(0.05, gap + (v_lead - v) * 0.01)
        x += v * 0.01
    return out


def _nothing(ctrl: Controller, k: int) -> None:
    pass


def _trouble(ctrl: Controller, k: int) -> None:
    """Solves that run out of iterations, then non-finite values where the controller
    keeps them (the previous command as the caller sets it, the disturbance estimate, the
    winding's resistance) and back."""
    ctrl.mpc.set_max_iter(2 if 40 <= k < 46 else ctrl.cfg.max_iter)
    if k in (60, 61):
        ctrl.u_prev = (math.nan, math.inf)[k - 60]
    if k == 80:
        ctrl.disturbance_v = math.nan
    if k == 81:
        ctrl.disturbance_v = 0.0
    if k == 90:
        ctrl._r_scale = math.inf
    if k == 91:
        ctrl._r_scale = 1.0


LOADS = (Effects(), Effects(aero_drag=0.8, load_force=-0.4), Effects(load_force=0.6))
"""Known loads the compiled feedforward computes too: none, drag with a pushing force, a
force alone."""


@needs_library
@pytest.mark.parametrize(("seed", "poke"), [(0, _nothing), (1, _trouble), (2, _trouble)])
def test_compiled_numerics_give_the_python_commands_on_drives(
    seed: int, poke: Callable[[Controller, int], None]
) -> None:
    cfg = load_config().control.in_simulated_time()
    vehicle = (_drawn(seed) if seed else ControlModel(load_config().vehicle)).params
    model = ControlModel(vehicle, LOADS[seed])
    compiled = Controller(model, cfg, TICKS)
    assert compiled.backend.startswith("compiled ("), compiled.backend
    calls = _counted(compiled)
    python = _python_controller(model, cfg)
    a, b = _drive(compiled, seed, 200, poke), _drive(python, seed, 200, poke)
    assert calls[0] > 100
    for k, (oa, ob) in enumerate(zip(a, b, strict=True)):
        _same(oa, ob, k)
        assert abs(oa.u) <= compiled.u_max
    modes = {o.mode for o in a}
    assert {"follow", "cruise"} <= modes  # and hold / fallback where the drive has them
    assert any(o.u_ff > 0.0 and o.estimate.v <= cfg.moving_speed for o in a)  # breakaway
    if poke is _trouble:
        assert any(o.fallback_reason is not None for o in a)


BAD = (math.nan, math.inf, -math.inf, 1e300, -1e300)


@needs_library
def test_the_command_is_finite_and_within_limits_whatever_arrives_on_both_paths() -> None:
    cfg = load_config().control.in_simulated_time()
    model = ControlModel(load_config().vehicle)
    ctrls = (Controller(model, cfg, TICKS), _python_controller(model, cfg))
    assert ctrls[0]._numerics is not None and ctrls[1]._numerics is None
    n = ctrls[0].forecast_steps
    good = {"v": 0.8, "gap": 0.9, "v_lead": 0.7, "x": 3.0}
    for field in ("v", "gap", "v_lead", "x", "u_prev", "disturbance_v", "forecast"):
        for bad in BAD:
            outs = []
            for ctrl in ctrls:
                for _ in range(3):  # a cycle to settle, then the bad value
                    ctrl.control(_estimate(**good))
                est = _estimate(**{**good, **({field: bad} if field in good else {})})
                if field in ("u_prev", "disturbance_v"):
                    setattr(ctrl, field, bad)
                fc = [0.5] * (n - 1) + [bad] if field == "forecast" else None
                o = ctrl.control(est, fc)
                ctrl.disturbance_v = 0.0
                assert math.isfinite(o.u) and abs(o.u) <= ctrl.u_max, (field, bad, o)
                outs.append(o)
            _same(outs[0], outs[1], (field, bad))


def test_constants_come_from_the_model_and_configuration() -> None:
    """Nothing physical is written in the C file: every constant it takes is named here
    and computed from the model and the configuration."""
    cfg = load_config().control
    model = _drawn(3)
    p = model.params
    values = dict(zip(CONSTANTS, constants(model, cfg, 6.0, 0.25, 0.004), strict=True))
    assert (values["R_m"], values["K_T"], values["K_v"], values["ratio"]) == (
        p.R_m, p.K_T, p.K_v, p.ratio,
    )  # fmt: skip
    assert (values["u_max"], values["du"], values["time_budget_s"]) == (6.0, 0.25, 0.004)
    assert (values["d_0"], values["v_set"], values["hold_gap_tol"]) == (
        cfg.d_0, cfg.v_set, cfg.hold_gap_tol,
    )  # fmt: skip
    source = (Path(__file__).parents[1] / "truckd/control/kernel/cycle_numerics.c").read_text()
    for v in (p.R_m, p.K_T, cfg.moving_speed, cfg.v_max, cfg.start_voltage, cfg.v_set, cfg.d_0):
        assert repr(v) not in source


@needs_library
@pytest.mark.parametrize(
    ("effects", "why"),
    [
        (Effects(hill_force=0.5, hill_length=2.0), "the model's feedforward has terrain"),
        (Effects(stribeck=0.003), "the model's feedforward has terrain"),
        (Effects(input_delay=0.02), "the model has an input delay"),
        (Effects(dead_zone=0.3), "the model has the driver map dead_zone"),
        (Effects(battery_sag=0.1), "the model has the driver map battery_sag"),
    ],
)
def test_a_model_the_compiled_numerics_do_not_serve_runs_python_and_says_why(
    effects: Effects, why: str
) -> None:
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle, effects), cfg, TICKS)
    assert ctrl._numerics is None
    assert ctrl.backend.startswith(f"MPC compiled; feedforward and command checks in Python ({why}")
    assert ctrl.control(_estimate(0.8, 0.9, 0.7, 1.0)).fallback_reason is None


@pytest.mark.usefixtures("no_library")
def test_without_the_library_the_numerics_run_python_and_say_why() -> None:
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    assert ctrl.backend == (
        "MPC python (libtruckd_mpc.so not built (make firmware)); feedforward and command "
        "checks in Python (the MPC runs its Python path); estimator in Python (the MPC runs "
        "its Python path)"
    )
    assert ctrl.control(_estimate(0.8, 0.9, 0.7, 1.0)).fallback_reason is None


@needs_library
def test_a_solve_wrapped_on_the_instance_is_called_through_the_python_path() -> None:
    """Fault injection wraps the MPC's solve: the controller then calls it (the compiled
    numerics would go around it)."""
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    calls = _counted(ctrl)
    seen: list[str] = []
    inner = ctrl.mpc.solve

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        seen.append("solve")
        return inner(*args, **kwargs)

    ctrl.mpc.solve = wrapped  # type: ignore[method-assign]
    assert ctrl.control(_estimate(0.8, 0.9, 0.7, 1.0)).fallback_reason is None
    assert seen == ["solve"] and calls[0] == 0
