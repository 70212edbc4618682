"""The move-blocked, condensed QP is the sparse QP restricted to blocked inputs: its
vectors equal the sparse ones condensed, its solution satisfies the sparse QP's dynamics
and bounds, and one step per block gives the sparse QP's optimum."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from truckd.control import condensed
from truckd.control.condensed import CondensedQp, block_lengths, max_block_steps
from truckd.control.config import ControlConfig
from truckd.control.mpc import MpcSolver
from truckd.control.qp import ControlModel, QpBuilder, QpInputs
from truckd.model.params import VehicleParams


def _inputs(rng: np.random.Generator, cfg: ControlConfig, lead: bool) -> QpInputs:
    n = cfg.horizon
    return QpInputs(
        x0=np.array([rng.uniform(-2, 2), rng.uniform(0, 2.3), rng.uniform(0.1, 3)]),
        u_prev=rng.uniform(-3, 6),
        v_lead=rng.uniform(0, 2, n),
        lead=lead,
        v_ref=rng.uniform(0, 2),
        v_cap=rng.uniform(1, 2.4),
        u_lo=-cfg.u_max,
        u_hi=cfg.u_max,
    )


@pytest.mark.parametrize(
    ("horizon", "blocks", "expected"),
    [
        (40, 8, (1, 1, 2, 4, 8, 8, 8, 8)),
        (20, 8, (1, 1, 2, 3, 3, 3, 3, 4)),
        (80, 8, (1, 1, 2, 4, 8, 16, 24, 24)),
        (5, 8, (1, 1, 1, 1, 1)),
        (40, 1, (40,)),
    ],
)
def test_block_lengths(horizon: int, blocks: int, expected: tuple[int, ...]) -> None:
    got = block_lengths(horizon, blocks)
    assert got == expected and sum(got) == horizon


@pytest.mark.parametrize(
    ("max_len", "expected"),
    [
        (8, (1, 1, 2, 4, 8, 8, 8, 8)),
        (5, (1, 1, 2, 4, 4, 4, 4, 4, 4, 4, 4, 4)),
        (3, (1, 1, 2, 2, 2, 3, 3, 2, 3, 3, 2, 3, 3, 2, 3, 3, 2)),
        (1, (1,) * 40),
    ],
)
def test_block_lengths_capped(max_len: int, expected: tuple[int, ...]) -> None:
    """No block longer than ``max_len``: the long ones split evenly, the sum kept."""
    got = block_lengths(40, 8, max_len)
    assert got == expected and sum(got) == 40 and max(got) <= max_len


def test_blocks_shorter_for_a_truck_with_a_short_mechanical_time_constant(
    params: VehicleParams,
) -> None:
    """``block_tau_fraction`` 0.5: the shipped truck keeps its 8 blocks (the compiled
    cycle's shape); a truck whose back-EMF settles faster (motor constant 1.3x: time
    constant / 1.69) holds each voltage for at most half of its time constant.  0 (the
    default): no limit."""
    cfg = dataclasses.replace(ControlConfig(), block_tau_fraction=0.5)
    tau = params.J_S * params.R_m / (params.K_T * params.K_v)
    assert max_block_steps(tau, cfg.period, 0.5) == 8
    assert max_block_steps(tau, cfg.period, 0.0) is None
    assert max_block_steps(0.001, cfg.period, 0.5) == 1
    shipped = MpcSolver(ControlModel(params), cfg).condensed
    assert shipped is not None and shipped.blocks == (1, 1, 2, 4, 8, 8, 8, 8)
    strong = params.replace(K_T=1.3 * params.K_T, K_v=1.3 * params.K_v)
    quick = MpcSolver(ControlModel(strong), cfg).condensed
    assert quick is not None and max(quick.blocks) == 4 and sum(quick.blocks) == cfg.horizon
    unlimited = MpcSolver(ControlModel(strong), ControlConfig()).condensed
    assert unlimited is not None and unlimited.blocks == (1, 1, 2, 4, 8, 8, 8, 8)


@pytest.mark.parametrize("mode", ["follow", "cruise"])
@pytest.mark.parametrize("lead", [True, False])
@pytest.mark.parametrize("one_speed", [False, True])
@pytest.mark.parametrize("lookahead", [0.0, 0.3])
def test_condensed_vectors_equal_the_sparse_ones_condensed(
    params: VehicleParams, mode: str, lead: bool, one_speed: bool, lookahead: float
) -> None:
    """``one_speed``: the lead at one speed over the horizon (no forecast), which fill
    computes with the lead's columns summed; ``lookahead``: the follow term on
    ``v + T a`` (``rel_speed_lookahead``, the spacing error's rate)."""
    cfg = dataclasses.replace(ControlConfig(), rel_speed_lookahead=lookahead)
    qp = QpBuilder(ControlModel(params), cfg)
    cq = CondensedQp(qp, block_lengths(cfg.horizon, 8))
    rng = np.random.default_rng(11)
    a_sparse = qp.A.toarray()
    for _ in range(5):
        inp = _inputs(rng, cfg, lead)
        if one_speed:
            inp = dataclasses.replace(inp, v_lead=np.full(cfg.horizon, rng.uniform(0, 2)))
        q, lo, hi = np.empty(cq.nw), np.empty(cq.m), np.empty(cq.m)
        cq.vectors_into(mode, inp, q, lo, hi)
        qs, ls, hs = qp.vectors(mode, inp)
        c = cq.C0 @ inp.x0 + cq.Cl @ inp.v_lead
        np.testing.assert_allclose(q, cq.ME.T @ (qs + qp.P[mode] @ c), rtol=1e-10, atol=1e-9)
        sel = qp.lay.r_gap + cq.state_sel
        ac = a_sparse[sel] @ c
        rows = cq.state_rows
        finite = ls[sel] > -1e20
        np.testing.assert_allclose(lo[rows][finite], (ls[sel] - ac)[finite], rtol=1e-12, atol=1e-12)
        assert np.all(lo[rows][~finite] < -1e20)
        finite = hs[sel] < 1e20
        np.testing.assert_allclose(hi[rows][finite], (hs[sel] - ac)[finite], rtol=1e-12, atol=1e-12)
        assert np.all(hi[rows][~finite] > 1e20)
        b0 = cq.block_rows[0]
        assert (lo[b0], hi[b0]) == (ls[qp.lay.r_u], hs[qp.lay.r_u])
        assert np.all(lo[cq.block_rows[1:]] == inp.u_lo)
        assert np.all(hi[cq.block_rows[1:]] == inp.u_hi)
        du = cfg.du_max * cfg.period
        assert np.all(lo[cq.change_rows] == -du) and np.all(hi[cq.change_rows] == du)
        # every row is one of these (the rows outside fill's product included)
        every = np.concatenate([cq.state_rows, cq.block_rows, cq.change_rows])
        assert np.array_equal(np.sort(every), np.arange(cq.m))
        # The cost of a blocked input sequence is the sparse cost of its expansion (up to
        # a constant): compare differences between two random sequences.
        w1, w2 = rng.normal(size=cq.nw), rng.normal(size=cq.nw)
        p = cq.P[mode].toarray()
        costs_c = [float(0.5 * w @ p @ w + q @ w) for w in (w1, w2)]
        zs = [cq.expand(w, inp.x0, inp.v_lead) for w in (w1, w2)]
        costs_s = [float(0.5 * z @ (qp.P[mode] @ z) + qs @ z) for z in zs]
        assert costs_c[0] - costs_c[1] == pytest.approx(costs_s[0] - costs_s[1], rel=1e-9)


def test_blocked_solution_satisfies_the_sparse_qp(params: VehicleParams) -> None:
    """The expanded solution meets the sparse QP's dynamics exactly, holds the inputs
    over the blocks, and is within the sparse bounds (to the solver's tolerance)."""
    cfg = dataclasses.replace(ControlConfig(), eps=1e-7, max_iter=50_000, time_budget_s=1.0)
    s = MpcSolver(ControlModel(params), cfg)
    assert s.condensed is not None
    qp = s.qp
    rng = np.random.default_rng(4)
    for k in range(10):
        inp = _inputs(rng, cfg, lead=k % 2 == 0)
        res = s.solve("follow" if k % 3 else "cruise", inp)
        z = s.last_solution
        assert res.ok and z is not None and res.u is not None and res.v is not None
        # the plan the cycle uses is the expanded solution's inputs and speeds
        n, u0 = qp.lay.N, qp.lay.u0
        np.testing.assert_allclose(res.u, z[u0 : u0 + n], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(res.v, qp.speeds(z), rtol=1e-12, atol=1e-12)
        _, lo, hi = qp.vectors("follow", inp)
        az = qp.A @ z
        dyn = slice(0, qp.lay.r_u)
        np.testing.assert_allclose(az[dyn], lo[dyn], atol=1e-9)
        assert np.all(az >= lo - 1e-4) and np.all(az <= hi + 1e-4)
        u = z[qp.lay.u0 : qp.lay.u0 + qp.lay.N]
        k0 = 0
        for length in s.condensed.blocks:
            assert np.ptp(u[k0 : k0 + length]) == 0.0
            k0 += length
        assert res.u0 == u[0]


@pytest.mark.parametrize("lookahead", [0.0, 0.3])
def test_one_step_per_block_is_the_sparse_optimum(params: VehicleParams, lookahead: float) -> None:
    """Condensing alone changes nothing: the same optimum as the sparse QP (with the
    follow term on the speed, and on the spacing error's rate)."""
    base = dataclasses.replace(
        ControlConfig(), eps=1e-7, max_iter=50_000, time_budget_s=1.0,
        rel_speed_lookahead=lookahead,
    )  # fmt: skip
    sparse = MpcSolver(ControlModel(params), dataclasses.replace(base, move_blocks=0))
    dense = MpcSolver(ControlModel(params), dataclasses.replace(base, move_blocks=base.horizon))
    rng = np.random.default_rng(9)
    for k in range(8):
        inp = _inputs(rng, base, lead=True)
        mode = "follow" if k % 2 else "cruise"
        a, b = sparse.solve(mode, inp), dense.solve(mode, inp)
        za, zb = sparse.last_solution, dense.last_solution
        assert a.ok and b.ok and za is not None and zb is not None
        assert a.u0 == pytest.approx(b.u0, abs=1e-4)
        np.testing.assert_allclose(
            za[: 3 * (base.horizon + 1)], zb[: 3 * (base.horizon + 1)], atol=1e-3
        )
        assert a.v is not None and b.v is not None
        np.testing.assert_allclose(a.v, b.v, atol=1e-3)


@pytest.mark.parametrize("blocks", [0, 8])
def test_a_kept_solution_is_not_overwritten_by_the_next_solve(
    params: VehicleParams, blocks: int
) -> None:
    """The solver keeps OSQP's solution arrays without copying them (the binding returns a
    new array on each access): the next solve must leave the previous result as it was."""
    cfg = dataclasses.replace(ControlConfig(), move_blocks=blocks, time_budget_s=1.0)
    s = MpcSolver(ControlModel(params), cfg)
    rng = np.random.default_rng(11)
    first = s.solve("follow", _inputs(rng, cfg, lead=True))
    assert first.ok and first.u is not None and first.v is not None
    u1, v1 = first.u.copy(), first.v.copy()
    z1 = s.last_solution
    second = s.solve("cruise", _inputs(rng, cfg, lead=False))
    assert second.ok and second.u is not None and second.v is not None
    assert not np.array_equal(second.v, v1)  # a different QP: the check can fail
    np.testing.assert_array_equal(first.u, u1)
    np.testing.assert_array_equal(first.v, v1)
    for kept in (first.u, first.v, z1):
        assert not np.shares_memory(s._warm[0], kept)


def test_the_plan_is_the_expanded_solutions_inputs_and_speeds(params: VehicleParams) -> None:
    """``plan`` (one product for the speeds, a gather for the inputs) gives the inputs and
    speeds of ``M E w + C0 x0 + Cl v_lead`` for the inputs of the last fill."""
    cfg = ControlConfig()
    qp = QpBuilder(ControlModel(params), cfg)
    cq = CondensedQp(qp, block_lengths(cfg.horizon, 8))
    rng = np.random.default_rng(12)
    n, u0 = cfg.horizon, qp.lay.u0
    for k in range(5):
        inp = _inputs(rng, cfg, lead=k % 2 == 0)
        assert cq.fill("follow" if k % 2 else "cruise", inp)
        w = rng.normal(size=cq.nw)
        ref = cq.ME @ w + cq.C0 @ inp.x0 + cq.Cl @ inp.v_lead
        u, v = cq.plan(w)
        np.testing.assert_allclose(u, ref[u0 : u0 + n], rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(v, qp.speeds(ref), rtol=1e-13, atol=1e-13)


def test_lists_and_arrays_fill_alike_and_bad_inputs_leave_the_vectors(
    params: VehicleParams,
) -> None:
    """The controller passes x0 and v_lead as lists (no numpy call per cycle): the same
    vectors as arrays give; a non-finite input is refused before anything is written; a
    wrong count is an error, not a silently shifted input."""
    cfg = ControlConfig()
    cq = CondensedQp(QpBuilder(ControlModel(params), cfg), block_lengths(cfg.horizon, 8))
    rng = np.random.default_rng(5)
    for lead in (True, False):
        inp = _inputs(rng, cfg, lead)
        as_lists = dataclasses.replace(inp, x0=inp.x0.tolist(), v_lead=inp.v_lead.tolist())
        assert cq.fill("follow", inp)
        ref = (cq.q_view.copy(), cq.lo_view.copy(), cq.hi_view.copy())
        filled = list(cq.filled)
        assert all(type(x) is float for x in filled)
        cq.fill("cruise", _inputs(rng, cfg, not lead))  # something else in between
        assert cq.fill("follow", as_lists)
        assert cq.filled == filled
        for got, want in zip((cq.q_view, cq.lo_view, cq.hi_view), ref, strict=True):
            np.testing.assert_array_equal(got, want)
        for bad in (math.nan, math.inf, 1e12):
            v_lead = [*as_lists.v_lead[:-1], bad]
            assert not cq.fill("follow", dataclasses.replace(as_lists, v_lead=v_lead))
            assert cq.filled == filled
            np.testing.assert_array_equal(cq.q_view, ref[0])
        with pytest.raises(ValueError, match="inputs"):
            cq.fill("follow", dataclasses.replace(as_lists, v_lead=as_lists.v_lead[1:]))


def _braking_or_capped(rng: np.random.Generator, cfg: ControlConfig, k: int) -> QpInputs:
    """Inputs whose optimum presses on the speed rows: fast under a low cap, or a lead
    stopping close ahead (the truck brakes to rest and the no-reverse rows hold it)."""
    inp = _inputs(rng, cfg, lead=k % 2 == 1)
    if k % 2 == 0:
        return dataclasses.replace(inp, x0=np.array([0.0, 2.3, 3.0]), v_cap=rng.uniform(0.5, 1.5))
    return dataclasses.replace(
        inp,
        x0=np.array([rng.uniform(0, 3), rng.uniform(0.5, 2.0), 0.45]),
        v_lead=np.zeros(cfg.horizon),
    )


@pytest.mark.parametrize("inertia", [1.0, 0.01])
def test_speed_rows_inside_a_block_never_bind(
    params: VehicleParams, monkeypatch: pytest.MonkeyPatch, inertia: float
) -> None:
    """The QP keeps each block's speed rows at its first and last step only: its optimum
    is the one with every step's speed rows (the speed is monotone within a block; with a
    hundredth of the inertia the motor's modes are complex but vanish within a period),
    on instances where those rows bind."""
    params = params.replace(J_S=params.J_S * inertia)
    cfg = dataclasses.replace(ControlConfig(), eps=1e-9, max_iter=100_000, time_budget_s=10.0)
    kept = MpcSolver(ControlModel(params), cfg, compiled=False)
    assert kept.condensed is not None and len(kept.condensed.speed_steps) == 14
    monkeypatch.setattr(
        condensed, "speed_steps", lambda ad, blocks, u_max, v_max: tuple(range(sum(blocks)))
    )
    every = MpcSolver(ControlModel(params), cfg, compiled=False)
    assert every.condensed is not None and every.condensed.m == kept.condensed.m + 52
    qp, n = every.qp, cfg.horizon
    rng = np.random.default_rng(21)
    binding = 0
    for k in range(16):
        inp = _braking_or_capped(rng, cfg, k)
        mode = "follow" if inp.lead else "cruise"
        a, b = kept.solve(mode, inp), every.solve(mode, inp)
        assert a.ok and b.ok and a.u is not None and b.u is not None
        np.testing.assert_allclose(a.u, b.u, atol=1e-5)
        z = every.last_solution
        assert z is not None
        _, lo, hi = qp.vectors(mode, inp)
        az = qp.A @ z
        rows = np.r_[qp.lay.r_vhi : qp.lay.r_vhi + n, qp.lay.r_vlo : qp.lay.r_vlo + n]
        binding += int(np.any(np.minimum(az[rows] - lo[rows], hi[rows] - az[rows]) < 1e-6))
    assert binding >= 8  # the speed rows bind in most instances: the comparison has teeth


def test_a_slow_electrical_pole_keeps_every_speed_row(params: VehicleParams) -> None:
    """Where the current's transient, or the motor's ringing, outlasts the period the
    speed need not be monotone within a block: every step keeps its speed rows."""
    cfg = ControlConfig()
    slow = dataclasses.replace(params, L_m=params.L_m * 20.0)
    cq = MpcSolver(ControlModel(slow), cfg, compiled=False).condensed
    assert cq is not None and cq.speed_steps == tuple(range(cfg.horizon))
    ringing = dataclasses.replace(params, L_m=params.L_m * 100.0)  # complex modes, |.| 0.9
    rq = MpcSolver(ControlModel(ringing), cfg, compiled=False).condensed
    assert rq is not None and rq.speed_steps == tuple(range(cfg.horizon))
    fast = MpcSolver(ControlModel(params), cfg, compiled=False).condensed
    assert fast is not None and cq.m == fast.m + 52
