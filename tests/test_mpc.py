"""The MPC: prediction model against the plant, first move against an independent solver
(CLARABEL, an interior-point method), terminal cost, feasibility, status handling and fallbacks."""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Iterator

import clarabel
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import sparse

from truckd.config.truck import load_config
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.estimator import Estimate
from truckd.control.lead import lead_horizon
from truckd.control.mpc import MpcSolver
from truckd.control.qp import ControlModel, QpInputs, prediction_model
from truckd.model.params import VehicleParams
from truckd.sim.plant import Plant

TICKS = load_config().ticks_per_rev
"""Encoder ticks per wheel revolution of the shipped configuration."""

FIRST_MOVE_TOL_V = 1e-3
"""OSQP at eps 1e-6 against CLARABEL: first moves agree to 1 mV (of a 14.4 V range); the
worst of these seeded instances is 0.1 mV (rho 0.03), so this is 10x margin."""


def tight(cfg: ControlConfig | None = None, **kw: float | int) -> ControlConfig:
    """A configuration that solves to high accuracy, in simulated time (no wall-clock budget)."""
    base = cfg or ControlConfig()
    return dataclasses.replace(base, eps=1e-6, max_iter=50_000, **kw).in_simulated_time()


def clarabel_first_move(solver: MpcSolver, mode: str, inp: QpInputs) -> float:
    """The QP the solver solves (P, q, A, l, u: the sparse one, or the move-blocked condensed
    one) solved by CLARABEL (an interior-point method)."""
    b, cq = solver.qp, solver.condensed
    if cq is None:
        q, lo, hi = b.vectors(mode, inp)
        p, a, i_u0 = b.P[mode].toarray(), b.A.toarray(), b.lay.u0
    else:
        q, lo, hi = np.empty(cq.nw), np.empty(cq.m), np.empty(cq.m)
        cq.vectors_into(mode, inp, q, lo, hi)
        p, a, i_u0 = cq.P[mode].toarray(), cq.A.toarray(), 0
    eq = (lo == hi) & (hi < 1e20)
    has_lo, has_hi = (lo > -1e20) & ~eq, (hi < 1e20) & ~eq
    # A z = u for the equality rows (the zero cone), then l <= A z <= u as the cone
    # constraints -A z + s = -l and A z + s = u with s >= 0 (the nonnegative cone)
    a_cone = sparse.csc_matrix(np.vstack([a[eq], -a[has_lo], a[has_hi]]))
    b_cone = np.concatenate([hi[eq], -lo[has_lo], hi[has_hi]])
    cones = [
        clarabel.ZeroConeT(int(eq.sum())),
        clarabel.NonnegativeConeT(b_cone.size - int(eq.sum())),
    ]
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    qp_solver = clarabel.DefaultSolver(
        sparse.triu(sparse.csc_matrix(p), format="csc"),
        q,
        a_cone,
        b_cone,
        cones,
        settings,
    )
    sol = qp_solver.solve()
    assert sol.status == clarabel.SolverStatus.Solved
    return float(sol.x[i_u0])


def random_inputs(rng: np.random.Generator, cfg: ControlConfig, n: int) -> QpInputs:
    v = rng.uniform(0.0, 2.3)
    u_prev = rng.uniform(-3.0, 6.0)
    ff = rng.choice([0.0, 0.45])
    return QpInputs(
        x0=np.array([rng.uniform(-2.0, 2.0), v, rng.uniform(0.1, 3.0)]),
        u_prev=u_prev - ff,
        v_lead=np.full(n, rng.uniform(0.0, 2.0)),
        lead=bool(rng.random() < 0.8),
        v_ref=cfg.v_set,
        v_cap=cfg.v_max,
        u_lo=-cfg.u_max - ff,
        u_hi=cfg.u_max - ff,
    )


def test_prediction_model_matches_the_plant_without_friction(params: VehicleParams) -> None:
    """One exact-ZOH step of the MPC's model equals the plant's exact stepping."""
    p = params.replace(K_coulomb=0.0, K_stiction=0.0)
    model = ControlModel(p)
    dt = 0.01
    pred = prediction_model(model, dt)
    plant = Plant(p)
    plant.reset(v=1.0, i=3.0)
    u, v_lead, gap0 = 4.0, 0.7, 1.0
    plant.command(u)
    plant.advance(dt)
    x0 = np.array([p.R_m * 3.0, 1.0, gap0])
    x1 = pred.Ad @ x0 + pred.bu * u + pred.bl * v_lead
    assert x1[1] == pytest.approx(plant.v, rel=1e-9, abs=1e-12)
    assert x1[0] / p.R_m == pytest.approx(plant.motor.i, rel=1e-9, abs=1e-9)
    assert x1[2] == pytest.approx(gap0 + v_lead * dt - plant.x, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("blocks", [0, 8, 40])
@pytest.mark.parametrize("mode", ["follow", "cruise"])
def test_first_move_equals_clarabel_on_random_instances(
    params: VehicleParams, mode: str, blocks: int
) -> None:
    """Sparse (0), move-blocked (8) and condensed with one step per block (40)."""
    cfg = tight(move_blocks=blocks)
    solver = MpcSolver(ControlModel(params), cfg)
    rng = np.random.default_rng(7 if mode == "follow" else 8)
    worst = 0.0
    for _ in range(12):
        inp = random_inputs(rng, cfg, cfg.horizon)
        res = solver.solve(mode, inp)
        assert res.ok, res.status
        ref = clarabel_first_move(solver, mode, inp)
        worst = max(worst, abs(res.u0 - ref))
    assert worst <= FIRST_MOVE_TOL_V


def test_default_tolerance_first_move_is_close_to_clarabel(params: VehicleParams) -> None:
    """At the shipped eps (5e-5), cold started, the first move is within 10 mV of the
    optimum."""
    cfg = dataclasses.replace(ControlConfig(), max_iter=10_000).in_simulated_time()
    solver = MpcSolver(ControlModel(params), cfg)
    rng = np.random.default_rng(3)
    for _ in range(8):
        inp = random_inputs(rng, cfg, cfg.horizon)
        solver.reset()
        res = solver.solve("follow", inp)
        assert res.ok
        assert abs(res.u0 - clarabel_first_move(solver, "follow", inp)) <= 0.01


def test_riccati_terminal_cost_makes_the_horizon_irrelevant_when_unconstrained(
    params: VehicleParams,
) -> None:
    """Near the equilibrium no constraint is active: N=15 and N=60 give the same first
    move (the DARE terminal cost is the exact infinite-horizon cost-to-go).  Without move
    blocking: blocks over different horizons are different input sequences."""
    model = ControlModel(params)
    moves = []
    for n in (15, 60):
        cfg = tight(horizon=n, move_blocks=0)
        s = MpcSolver(model, cfg)
        v = 1.0
        u_ss = params.K_v * params.omega(v)
        inp = _inputs(cfg, (0.0, v, cfg.d_0 + cfg.time_headway * v + 0.02), u_ss, v)
        res = s.solve("follow", inp)
        assert res.ok
        moves.append(res.u0 - u_ss)
    assert moves[0] != 0.0
    assert moves[0] == pytest.approx(moves[1], rel=1e-3, abs=1e-5)


@settings(max_examples=40, deadline=None)
@given(
    gap=st.floats(-1.0, 5.0),
    v=st.floats(-0.5, 4.0),
    u_prev=st.floats(-7.2, 7.2),
    v_lead=st.floats(0.0, 3.0),
)
def test_qp_is_never_infeasible(
    tight_solver: MpcSolver, gap: float, v: float, u_prev: float, v_lead: float
) -> None:
    """Gap below the minimum, speed over the limit, command at a bound: still solvable
    (state constraints are soft; input bounds and rate are met by holding u_prev)."""
    s = tight_solver
    cfg = s.cfg
    inp = _inputs(cfg, (0.0, v, gap), u_prev, v_lead)
    res = s.solve("follow", inp)
    assert res.ok, res.status
    assert -cfg.u_max - 1e-3 <= res.u0 <= cfg.u_max + 1e-3
    assert abs(res.u0 - u_prev) <= cfg.du_max * cfg.period + 1e-3


def _default_params() -> VehicleParams:
    from truckd.config.truck import load_config

    return load_config().vehicle


@pytest.fixture(scope="module")
def tight_solver() -> Iterator[MpcSolver]:
    """One solver for the module's property test (warm-started from example to example,
    as in the loop), released with the module: the compiled cycle has a few instances per
    process, and a solver held by a module global would keep one for the whole run."""
    yield MpcSolver(ControlModel(_default_params()), tight())


def _estimate(v: float, gap: float, v_lead: float, lead: bool = True) -> Estimate:
    return Estimate(
        v=v,
        speed_valid=True,
        gap=gap,
        v_lead=v_lead,
        lead_valid=lead,
        lead_status="tracking" if lead else "none",
        gap_std=0.01,
        outliers=0,
        reinits=0,
        encoder_samples=10,
        range_samples=10,
    )


def test_solver_failure_holds_the_plan_then_brakes(params: VehicleParams) -> None:
    cfg = dataclasses.replace(ControlConfig(), plan_hold_steps=3).in_simulated_time()
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    est = _estimate(1.2, 1.12, 1.2)
    for _ in range(5):
        good = ctrl.control(est)
    assert good.fallback_reason is None
    plan = [] if ctrl._plan is None else ctrl._plan.tolist()
    # From now on the solver reports failure (as OSQP would at its iteration limit).
    ctrl.mpc.set_max_iter(1)
    outs = [ctrl.control(est) for _ in range(6)]
    assert [o.fallback_reason is not None for o in outs] == [True] * 6
    assert all(o.fallback_reason.endswith(":plan") for o in outs[:3] if o.fallback_reason)
    assert all(o.fallback_reason.endswith(":brake") for o in outs[3:] if o.fallback_reason)
    # The held moves are the previous plan's, shifted (plus the same feedforward).
    assert outs[0].u_mpc == pytest.approx(plan[1], abs=1e-9)
    assert outs[1].u_mpc == pytest.approx(plan[2], abs=1e-9)
    assert outs[-1].mode == "fallback" and outs[-1].u < outs[2].u
    assert outs[-1].solver_failures == 6 and outs[-1].braking_cycles == 3


@settings(max_examples=60, deadline=None)
@given(
    v=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-5, 5)),
    gap=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1, 10)),
    v_lead=st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.floats(-1, 5)),
    lead=st.booleans(),
    valid=st.booleans(),
)
def test_command_is_always_finite_and_within_limits(
    default_controller: Controller, v: float, gap: float, v_lead: float, lead: bool, valid: bool
) -> None:
    ctrl = default_controller
    before = ctrl.u_prev
    est = dataclasses.replace(_estimate(v, gap, v_lead, lead), speed_valid=valid)
    out = ctrl.control(est)
    assert math.isfinite(out.u)
    assert abs(out.u) <= ctrl.u_max + 1e-12
    assert abs(out.u - before) <= ctrl.cfg.du_max * ctrl.cfg.period + 1e-9


@pytest.fixture(scope="module")
def default_controller() -> Iterator[Controller]:
    """One controller carried through the property test's examples (its state too, as in
    the loop), released with the module (see :func:`tight_solver`)."""
    yield Controller(ControlModel(_default_params()), ControlConfig(), TICKS)


def test_lead_lost_stop_policy_brakes_and_cruise_policy_holds(params: VehicleParams) -> None:
    v = 1.5
    u_hold = params.K_v * params.omega(v)
    for policy in ("stop", "cruise"):
        cfg = dataclasses.replace(ControlConfig(), on_lead_lost=policy).in_simulated_time()
        ctrl = Controller(ControlModel(params), cfg, TICKS)
        ctrl.u_prev = u_hold
        out = ctrl.control(_estimate(v, math.nan, math.nan, lead=False))
        assert out.fallback_reason is None
        if policy == "stop":
            assert out.mode == "stop" and out.u < u_hold - 1.0
        else:
            assert out.mode == "cruise" and out.u > u_hold  # towards v_set = 1.8 m/s


def test_lead_forecast_hook_changes_the_plan(params: VehicleParams) -> None:
    """A lead forecast to stop makes the plan stop; the constant-speed default holds speed."""
    cfg = ControlConfig().in_simulated_time()
    est = _estimate(1.2, 1.12, 1.2)
    end_speeds = []
    for forecast in (None, list(np.linspace(1.2, 0.0, cfg.horizon))):
        ctrl = Controller(ControlModel(params), cfg, TICKS)
        ctrl.u_prev = params.K_v * params.omega(1.2)
        assert ctrl.control(est, forecast).fallback_reason is None
        z = ctrl.mpc.last_solution
        assert z is not None
        end_speeds.append(ctrl.mpc.qp.plan(z)[1][-1])
    assert end_speeds[0] == pytest.approx(1.2, abs=0.05)
    assert end_speeds[1] < end_speeds[0] - 0.3


def test_a_lead_forecast_is_padded_capped_and_refused_when_not_finite(
    params: VehicleParams,
) -> None:
    """What the QP is given as the lead's speed: a short forecast holds its last value, a
    forecast above the cap or below zero is clipped, and one with a NaN or an infinity is
    not used at all (the estimate held constant instead)."""
    cfg = ControlConfig().in_simulated_time()
    n = cfg.horizon
    est = _estimate(1.2, 1.12, 1.0)
    cap = cfg.v_set
    horizon = lead_horizon
    assert horizon(est, [0.5, 0.4], n, cap) == [0.5] + [0.4] * (n - 1)
    assert horizon(est, [9.0, -1.0, 0.7], n, cap) == [cap, 0.0] + [0.7] * (n - 2)
    for bad in (math.nan, math.inf, -math.inf):
        assert horizon(est, [0.5, bad, 0.4], n, cap) == [min(1.0, cap)] * n
    assert horizon(est, None, n, 0.8) == [0.8] * n
    assert all(type(x) is float for x in horizon(est, list(np.linspace(1, 0, n)), n, cap))
    # and what the solver then saw: the filled inputs end with the capped forecast
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    ctrl.u_prev = params.K_v * params.omega(1.2)
    assert ctrl.control(est, [0.5, math.nan]).fallback_reason is None
    cq = ctrl.mpc.condensed
    assert cq is not None and cq.filled[-n:] == [min(1.0, cap)] * n


def _inputs(
    cfg: ControlConfig,
    x0: tuple[float, float, float] = (0.0, 1.2, 1.0),
    u_prev: float = 2.0,
    v_lead: float = 1.0,
) -> QpInputs:
    """Follow-mode inputs with a lead at constant speed and the configured limits."""
    return QpInputs(
        x0=np.array(x0),
        u_prev=u_prev,
        v_lead=np.full(cfg.horizon, v_lead),
        lead=True,
        v_ref=cfg.v_set,
        v_cap=cfg.v_max,
        u_lo=-cfg.u_max,
        u_hi=cfg.u_max,
    )


def test_time_limit_keeps_the_iterate_as_warm_start_other_failures_restart_cold(
    params: VehicleParams,
) -> None:
    cfg = dataclasses.replace(ControlConfig(), time_budget_s=1e-7)
    s = MpcSolver(ControlModel(params), cfg)
    res = s.solve("follow", _inputs(cfg))
    assert not res.ok and "time limit" in res.status
    assert s.has_warm_start and s.last_solution is None
    cfg = dataclasses.replace(ControlConfig(), max_iter=5).in_simulated_time()
    s = MpcSolver(ControlModel(params), cfg)
    res = s.solve("follow", _inputs(cfg))
    assert not res.ok and "maximum iterations" in res.status
    assert not s.has_warm_start


def test_without_any_plan_a_failure_holds_the_last_command_then_brakes(
    params: VehicleParams,
) -> None:
    cfg = dataclasses.replace(ControlConfig(), max_iter=1, plan_hold_steps=2).in_simulated_time()
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    ctrl.u_prev = 2.5
    outs = [ctrl.control(_estimate(1.2, 1.12, 1.2)) for _ in range(4)]
    reasons = [o.fallback_reason or "" for o in outs]
    assert [r.rsplit(":", 1)[-1] for r in reasons] == ["hold", "hold", "brake", "brake"]
    assert outs[0].u == pytest.approx(2.5) and outs[1].u == pytest.approx(2.5)
    assert outs[3].u < 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_speed_marked_valid_is_no_speed(params: VehicleParams, bad: float) -> None:
    """Taking it as 0 m/s would plan for a truck at rest (breakaway kick, no braking)
    while it may be moving: the fallback runs instead, and the command stays in limits."""
    cfg = ControlConfig().in_simulated_time()
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    ctrl.u_prev = 3.0
    out = ctrl.control(_estimate(bad, 0.5, 1.0))
    assert out.fallback_reason is not None and out.solver_status == "not-run"
    assert math.isfinite(out.u) and abs(out.u - 3.0) <= cfg.du_max * cfg.period + 1e-12


def test_standstill_hold_enters_at_rest_and_releases_with_hysteresis(
    params: VehicleParams,
) -> None:
    """At rest behind a stopped lead within d_0 + hold_gap_tol: 0 V, mode hold, no solve.
    Noise between the entry and release thresholds keeps the hold; a release condition must
    last hold_release_cycles; then the MPC starts the truck with the breakaway feedforward."""
    cfg = ControlConfig().in_simulated_time()
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    ctrl.u_prev = 0.4  # the creep's last command
    gap = cfg.d_0 + 0.8 * cfg.hold_gap_tol
    out = ctrl.control(_estimate(0.0, gap, 0.0))
    assert out.mode == "hold" and out.u == 0.0 and out.u_ff == 0.0
    assert out.solve_iterations == 0 and out.solver_status == "not-run"
    assert out.fallback_reason is None
    between_v = 0.5 * (cfg.hold_lead_speed + cfg.hold_release_speed)
    between_gap = cfg.d_0 + 0.5 * (cfg.hold_gap_tol + cfg.hold_release_gap)
    for k in range(50):
        noisy = _estimate(0.0, between_gap if k % 2 else gap, between_v if k % 3 else 0.0)
        out = ctrl.control(noisy)
        assert out.mode == "hold" and out.u == 0.0
    # A lead lost while holding keeps the hold (it was last seen stopped just ahead).
    assert ctrl.control(_estimate(0.0, math.nan, math.nan, lead=False)).mode == "hold"
    # Release speed exceeded for one cycle less than required, then broken: still held.
    going = _estimate(0.0, gap, 1.5 * cfg.hold_release_speed)
    for _ in range(cfg.hold_release_cycles - 1):
        assert ctrl.control(going).mode == "hold"
    assert ctrl.control(_estimate(0.0, gap, 0.0)).mode == "hold"
    for _ in range(cfg.hold_release_cycles - 1):
        assert ctrl.control(going).mode == "hold"
    out = ctrl.control(going)
    assert out.mode == "follow" and out.solve_iterations > 0
    assert out.u_ff > 0.0 and out.u > 0.0  # the start, with the breakaway feedforward
    # Not re-entered while the truck is still at rest and the lead goes.
    assert ctrl.control(going).mode == "follow"


def test_standstill_hold_not_entered_when_moving_far_or_lead_moving(
    params: VehicleParams,
) -> None:
    cfg = ControlConfig().in_simulated_time()
    near = cfg.d_0 + 0.5 * cfg.hold_gap_tol
    for est in (
        _estimate(2.0 * cfg.moving_speed, near, 0.0),  # still moving
        _estimate(0.0, cfg.d_0 + 1.5 * cfg.hold_gap_tol, 0.0),  # too far: close up first
        _estimate(0.0, near, 2.0 * cfg.hold_lead_speed),  # lead moving
        _estimate(0.0, math.nan, math.nan, lead=False),  # no lead
    ):
        ctrl = Controller(ControlModel(params), cfg, TICKS)
        assert ctrl.control(est).mode != "hold"
    # A gap below d_0 (stopped short) is held too: never reverse to open it.
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    assert ctrl.control(_estimate(0.0, cfg.d_min + 0.01, 0.0)).mode == "hold"


def test_hold_thresholds_must_have_hysteresis() -> None:
    assert ControlConfig().validate() is None
    bad_gap = dataclasses.replace(ControlConfig(), hold_release_gap=0.05, hold_gap_tol=0.05)
    assert "hold_release_gap" in (bad_gap.validate() or "")
    bad_v = dataclasses.replace(ControlConfig(), hold_release_speed=0.05, hold_lead_speed=0.05)
    assert "hold_release_speed" in (bad_v.validate() or "")


@pytest.mark.parametrize("blocks", [8, 0])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 1e308, 2e9])
@pytest.mark.parametrize("field", ["x0", "v_lead", "u_prev", "v_ref", "v_cap", "u_lo", "u_hi"])
def test_a_non_finite_or_huge_input_is_refused_before_the_solver(
    params: VehicleParams, blocks: int, bad: float, field: str
) -> None:
    """Any input NaN, infinite or beyond anything physical (qp.INPUT_LIMIT; 1e308 values
    whose sums overflow too) makes the solve fail with ``non-finite-input`` and no
    solution; the solver is not run, and the next good input solves."""
    cfg = ControlConfig(move_blocks=blocks).in_simulated_time()
    solver = MpcSolver(ControlModel(params), cfg)
    rng = np.random.default_rng(5)
    good = random_inputs(rng, cfg, solver.horizon)
    assert solver.solve("follow", good).ok
    if field in ("x0", "v_lead"):
        arr = getattr(good, field).copy()
        arr[int(rng.integers(arr.size))] = bad
        if bad == 1e308:  # every value: the sums overflow
            arr[:] = bad
        inp = dataclasses.replace(good, **{field: arr})
    else:
        inp = dataclasses.replace(good, **{field: bad})
        if bad == 1e308:
            inp = dataclasses.replace(inp, x0=np.full(3, bad))
    res = solver.solve("follow", inp)  # and no numpy warning (errors in this suite)
    assert (res.ok, res.status, res.u, res.v) == (False, "non-finite-input", None, None)
    assert math.isnan(res.u0) and res.iterations == 0
    assert solver.solve("follow", good).ok


def test_a_stale_speed_ramps_to_zero_volts_never_brakes_on_it(params: VehicleParams) -> None:
    """The last speed braked on, open loop, drove a truck that had stopped backwards (the
    estimator refusing a rebooted microcontroller's samples): without a speed the command
    goes to 0 V at the rate limit and stays there, never below."""
    cfg = ControlConfig().in_simulated_time()
    ctrl = Controller(ControlModel(params), cfg, TICKS)
    ctrl.u_prev = 3.0
    stale = dataclasses.replace(_estimate(1.25, 1.0, 1.25), speed_valid=False)
    outs = [ctrl.control(stale) for _ in range(300)]
    assert all(o.fallback_reason == "speed_stale:zero" for o in outs)
    du = cfg.du_max * cfg.period
    us = [3.0] + [o.u for o in outs]
    assert all(0.0 <= u <= 3.0 for u in us)
    assert all(abs(b - a) <= du + 1e-12 for a, b in itertools.pairwise(us))
    assert us[-1] == 0.0
