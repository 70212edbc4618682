"""The estimator's update compiled (truckd/control/cestimator.py,
truckd/control/kernel/estimator.c) gives the Python estimator's estimates, field for
field, on the recorded replay and on hostile samples (NaN and infinite times and
distances, huge and wrapping counters, time going backwards, clock restarts, glitches, a
cut-in); the controller's decisions in the same call (truckd_cycle_run) give the Python
controller's commands on drives through its step; the comparison fails where the
compiled estimator differs; without the library the estimator is Python's and says so."""

from __future__ import annotations

import dataclasses
import math
import random
from pathlib import Path

import numpy as np
import pytest
from test_cycle_numerics import (  # noqa: F401 - the autouse fixture applies here too
    DATA,
    TICKS,
    _counted,
    _python_controller,
    _same,
    _trouble,
    garbage_solvers_give_theirs_back,
    needs_library,
)

from truckd.config.truck import load_config
from truckd.control import mpc as mpc_module
from truckd.control.cestimator import CONSTANTS, CompiledEstimator, constants
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.estimator import EncoderSample, Estimate, Estimator, RangeSample
from truckd.control.mpc import MpcSolver
from truckd.control.output import ControlOutput
from truckd.control.qp import ControlModel
from truckd.runtime.replay import cycle_from_params
from truckd.runtime.rxlog import read_rx_log


def _differences(a: Estimate, b: Estimate) -> list[str]:
    """The fields in which two estimates differ (NaN equals NaN; types too)."""
    out = []
    for f in dataclasses.fields(Estimate):
        x, y = getattr(a, f.name), getattr(b, f.name)
        nan = isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y)
        if not (nan or (x == y and type(x) is type(y))):
            out.append(f"{f.name}: {x!r} != {y!r}")
    return out


@needs_library
def test_the_compiled_estimator_gives_the_python_estimates_on_the_recorded_replay(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    t0, params, cycles = read_rx_log(DATA / "run.rx.jsonl")
    cycles = list(cycles)
    compiled = cycle_from_params(params, t0, "compiled")
    init = MpcSolver.__init__

    def python(self: MpcSolver, m: ControlModel, c: ControlConfig, **_: bool) -> None:
        init(self, m, c, compiled=False)

    with monkeypatch.context() as mp:
        mp.setattr(mpc_module.MpcSolver, "__init__", python)
        reference = cycle_from_params(params, t0, "python")
    assert isinstance(compiled.controller.estimator, CompiledEstimator)
    assert isinstance(reference.controller.estimator, Estimator)
    assert compiled.controller.backend.startswith("compiled (estimator, decisions,")
    u = []
    for k, inp in enumerate(cycles):
        a, b = compiled.step(inp), reference.step(inp)
        assert a.control is not None and b.control is not None
        assert not _differences(a.control.estimate, b.control.estimate), k
        assert abs(a.command.voltage - b.command.voltage) <= 1e-9, k
        u.append(a.command.voltage)
    last = a.control.estimate
    assert last.encoder_samples > 250 and last.range_samples > 120 and max(u) > 1.0


def _hostile(seed: int, n: int) -> list[tuple[float, list[EncoderSample], list[RangeSample]]]:
    """Cycles of samples a broken link or firmware could deliver: mostly a truck driving
    behind a lead, with NaN and infinite times, time going backwards, the sample clock
    repeating, running ahead, restarting and wrapping; counters wrapping, huge, negative,
    resetting and glitching for one sample; a wheel unhealthy; ranges missing, NaN,
    infinite, negative, too close or too far, outliers and a new target that stays."""
    rng = random.Random(seed)
    mod_t, mod_ticks = 6.5536, 65536
    t, ts, x, gap, tick0 = 100.0, 6.4, 0.0, 1.0, mod_ticks - 300
    cycles = []
    for k in range(n):
        t += 0.01 if rng.random() > 0.03 else rng.choice([-0.5, -0.01, 0.0, 0.3, 2.0])
        ts = (ts + 0.01) % mod_t if rng.random() > 0.04 else rng.choice([0.0, ts - 0.02, ts + 1.0])
        x += 0.01 * (1.0 + math.sin(k / 40.0))
        ticks = tick0 + math.floor(x / 5e-4)
        left, right = ticks % mod_ticks, ticks % mod_ticks
        roll = rng.random()
        if roll < 0.02:
            left = rng.choice([2**70, -(2**65), 0, left + 3000, -1])
        elif roll < 0.03:
            tick0 -= 2000  # the counters reset
        t_cycle = rng.choice([math.nan, math.inf, -math.inf]) if rng.random() < 0.01 else t
        st = rng.choice([math.nan, math.inf, 1e300]) if rng.random() < 0.01 else ts
        encoders = [
            EncoderSample(left, right, st, rng.random() > 0.05, rng.random() > 0.05)
            for _ in range(rng.choice([0, 1, 1, 1, 2]))
        ]
        gap += 0.01 * math.cos(k / 30.0)
        d: float | None = gap + rng.gauss(0.0, 0.005)
        roll = rng.random()
        if roll < 0.05:
            d = rng.choice([None, math.nan, math.inf, -math.inf, -0.5, 0.01, 50.0, d + 0.6])
        elif 300 <= k % 700 < 320:
            d = gap + 0.5  # a cut-in: a new target that stays
        ranges = [RangeSample(d, st) for _ in range(rng.choice([0, 1, 1, 2]))]
        cycles.append((t_cycle, encoders, ranges))
    return cycles


@needs_library
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_compiled_estimator_gives_the_python_estimates_on_hostile_samples(seed: int) -> None:
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    compiled = ctrl.estimator
    assert isinstance(compiled, CompiledEstimator)
    python = Estimator(cfg.estimator, load_config().vehicle.r_w, TICKS)
    assert python.tick_len == compiled.tick_len
    for k, (t, encoders, ranges) in enumerate(_hostile(seed, 1500)):
        a, b = compiled.cycle(t, encoders, ranges), python.cycle(t, encoders, ranges)
        assert not _differences(a, b), (k, _differences(a, b))
    # the samples reached every rule
    assert b.speed_restarts > 5 and b.speed_glitches > 0 and b.outliers > 10 and b.reinits > 0
    assert b.encoder_samples > 1000 and b.range_samples > 1000


@needs_library
def test_a_cycle_of_many_samples_gives_the_python_estimate() -> None:
    """More samples in one cycle (a loop that was late) than the inputs first held: they
    grow, the state stays."""
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    compiled = ctrl.estimator
    assert isinstance(compiled, CompiledEstimator)
    python = Estimator(cfg.estimator, load_config().vehicle.r_w, TICKS)
    size = compiled.inputs.size
    for k, (t, encoders, ranges) in enumerate(_hostile(3, 200)):
        if k % 50 == 49:  # the next 40 cycles' samples at once
            batch = _hostile(3, 240)[k : k + 40]
            encoders = [e for _, es, _ in batch for e in es]
            ranges = [r for _, _, rs in batch for r in rs]
        a, b = compiled.cycle(t, encoders, ranges), python.cycle(t, encoders, ranges)
        assert not _differences(a, b), k
    assert compiled.inputs.size > size and b.encoder_samples > 200


@needs_library
def test_the_comparison_fails_where_the_compiled_estimator_differs() -> None:
    """One constant of the compiled estimator a little off (the own-speed filter's process
    noise): the comparison finds the estimates differ."""
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    compiled = ctrl.estimator
    assert isinstance(compiled, CompiledEstimator)
    compiled._consts[CONSTANTS.index("speed_accel_std")] *= 1.0 + 1e-12
    compiled.reset()
    python = Estimator(cfg.estimator, load_config().vehicle.r_w, TICKS)
    differ = [
        k
        for k, (t, encoders, ranges) in enumerate(_hostile(0, 300))
        if _differences(compiled.cycle(t, encoders, ranges), python.cycle(t, encoders, ranges))
    ]
    assert len(differ) > 100


def _drive(
    ctrls: tuple[Controller, Controller], n: int, trouble: bool
) -> list[tuple[ControlOutput, ControlOutput]]:
    """A drive through both controllers' step on the same encoder and range samples (the
    truck moved by the first one's commands): a lead that stops (the standstill hold),
    goes and disappears for a while; ``trouble``: :func:`test_cycle_numerics._trouble`."""
    rng = np.random.default_rng(5)
    tick_len = ctrls[0].estimator.tick_len
    v, x, x_lead, out = 0.0, 0.0, 1.2, []
    for k in range(n):
        t = 0.01 * k
        # at 0.8 m/s, stopping from 0.8 s, standing from 1.2 s to 3 s, going again
        v_lead = max(0.0, 0.8 - 0.02 * max(k - 80, 0)) if k < 300 else min(0.8, 0.01 * (k - 300))
        x_lead += v_lead * 0.01
        ticks = math.floor(x / tick_len) % 65536
        enc = [EncoderSample(ticks, ticks, t % 6.5536)]
        seen = not (420 <= k < 460 or 820 <= k < 860)
        rngs = [RangeSample(x_lead - x + float(rng.normal(0.0, 0.003)) if seen else None, t)]
        headway = None if k % 7 else 0.3 + 0.01 * (k % 30)
        pair = []
        for ctrl in ctrls:
            if trouble:
                _trouble(ctrl, k)
            pair.append(ctrl.step(t, enc, rngs, None, headway))
        o = pair[0]
        out.append((pair[0], pair[1]))
        v = max(0.0, v + 0.03 * (o.u - o.u_ff)) if o.u > 0.3 else max(0.0, v - 0.05)
        x += v * 0.01
    return out


def _decided_in_python(model: ControlModel, cfg: ControlConfig) -> Controller:
    """A controller with the compiled MPC and numerics whose estimator and decisions run
    in Python (the same solves as the one call's, from the same inputs)."""
    ctrl = Controller(model, cfg, TICKS)
    ctrl._fused = None
    ctrl.estimator = Estimator(cfg.estimator, model.params.r_w, TICKS)
    return ctrl


@needs_library
@pytest.mark.parametrize(
    ("on_lost", "gain", "trouble", "reference"),
    [
        ("cruise", 0.0, False, "python"),
        ("stop", 0.0, True, "python"),
        ("cruise", 0.02, False, "decided in python"),
        ("stop", 0.02, True, "decided in python"),
    ],
)
def test_the_decisions_in_the_compiled_call_give_the_python_commands(
    on_lost: str, gain: float, trouble: bool, reference: str
) -> None:
    """Against the Python path (MPC and all), and, with the offset-free action on (whose
    integrator adds up the two MPC paths' rounding), against the compiled MPC and numerics
    with the estimator and the decisions in Python: the same solves, bit for bit."""
    cfg = dataclasses.replace(
        load_config().control.in_simulated_time(), on_lead_lost=on_lost, disturbance_gain=gain
    )
    model = ControlModel(load_config().vehicle)
    if reference == "python":
        other = _python_controller(model, cfg)
    else:
        other = _decided_in_python(model, cfg)
    compiled = Controller(model, cfg, TICKS)
    assert compiled.backend.startswith("compiled (estimator, decisions,"), compiled.backend
    calls = _counted(compiled)
    exact = reference != "python"
    # (the two MPC paths' warm starts carry their rounding on: the Python path is compared
    # over a shorter drive, 1e-9 V holds there)
    pairs = _drive((compiled, other), 900 if exact else 480, trouble)
    for k, (oa, ob) in enumerate(pairs):
        _same(oa, ob, k)
        assert not _differences(oa.estimate, ob.estimate), k
        da, db = oa.disturbance_v, ob.disturbance_v
        both_nan = math.isnan(da) and math.isnan(db)
        assert both_nan or (da == db if exact else abs(da - db) <= 1e-9), k
        assert oa.u == ob.u or not exact, k
    assert calls[0] > 300  # most cycles went through the one call to the solve
    a = [oa for oa, _ in pairs]
    modes = {o.mode for o in a}
    assert {"follow", "cruise" if on_lost == "cruise" else "stop"} <= modes, modes
    if gain > 0.0:
        assert any(abs(o.disturbance_v) > 0.01 for o in a)
    else:  # (the offset-free action keeps the truck off the standstill hold's gap)
        assert "hold" in modes
    if trouble:
        assert any(o.fallback_reason is not None for o in a)


def test_the_estimator_constants_come_from_the_configuration() -> None:
    """No configured value is written in the C file: each constant it takes is named and
    comes from the estimator's configuration and tick length."""
    cfg = dataclasses.replace(load_config().control.estimator, gate_sigma=3.5, reinit_count=7)
    values = dict(zip(CONSTANTS, constants(cfg, 0.002), strict=True))
    assert (values["gate_sigma"], values["reinit_count"], values["tick_len"]) == (3.5, 7.0, 0.002)
    assert values["r_tick"] == 0.002 * 0.002 / 12.0
    source = (Path(__file__).parents[1] / "truckd/control/kernel/estimator.c").read_text()
    default = load_config().control.estimator
    for v in (
        default.sample_time_modulo, default.lead_timeout_s, default.speed_max,
        default.accel_max, default.lead_accel_std, default.ticks_modulo,
    ):  # fmt: skip
        assert repr(v) not in source


@pytest.mark.usefixtures("no_library")
def test_without_the_library_the_estimator_is_python_and_says_why() -> None:
    cfg = load_config().control.in_simulated_time()
    ctrl = Controller(ControlModel(load_config().vehicle), cfg, TICKS)
    assert isinstance(ctrl.estimator, Estimator)
    assert ctrl.backend.endswith("estimator in Python (the MPC runs its Python path)")
