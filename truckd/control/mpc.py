"""Warm-started OSQP MPC: set up once per mode, vectors updated every cycle.

One OSQP instance per cost mode (``follow``, ``cruise``) is set up at construction;
each cycle only ``q``, ``l``, ``u`` are updated and the solver is warm started from the
previous solution (shifted one step in the sparse form).  With ``move_blocks`` > 0 the QP
solved is the move-blocked, condensed one of :mod:`truckd.control.condensed` (10
variables instead of 165 at N = 40); its solution is mapped back to the sparse layout, so
:class:`MpcResult` and the plan look the same either way.  The move-blocked QP's cycle runs
compiled when the library is built (:mod:`truckd.control.ccycle`; :attr:`MpcSolver.backend`
says which path runs and why).

The status is checked every cycle: anything but ``solved`` (or ``solved inaccurate``,
counted) within the time budget (OSQP's ``time_limit``; the solver's own run time is
checked as well) is a failure the caller must handle (see
:class:`truckd.control.controller.Controller`).  No clock here: times come from OSQP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from truckd.control import ccycle
from truckd.control.condensed import CondensedQp, block_lengths, max_block_steps
from truckd.control.config import ControlConfig
from truckd.control.frozen import fast_init
from truckd.control.qp import MODES, ControlModel, QpBuilder, QpInputs, Vec, inputs_ok


@fast_init
@dataclass(frozen=True)
class MpcResult:
    """Outcome of one solve.

    ``ok`` solved within budget with a finite solution; ``u0`` first move (V, NaN when
    not ok); ``status`` OSQP's status text (or ``"overrun"``/``"non-finite"``);
    ``iterations``; ``run_time_s`` OSQP's own measured update+solve time (s); when ok,
    the plan: ``u`` the inputs ``u_0 .. u_{N-1}`` (V, ``u_0`` the first move) and ``v``
    the predicted speeds ``v_0 .. v_N`` (m/s), else None.  The whole solution vector:
    :attr:`MpcSolver.last_solution`.
    """

    ok: bool
    u0: float
    status: str
    iterations: int
    run_time_s: float
    u: Vec | None = None
    v: Vec | None = None


_MODE_INDEX = {mode: k for k, mode in enumerate(MODES)}
"""The compiled cycle's number of each mode."""

_USABLE = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
"""Statuses whose solution is used.  ``solved inaccurate`` met OSQP's relaxed (10x)
tolerances at the iteration limit: good to about 1e-3 V, counted in ``inaccurate``."""

_USABLE_VALUES = frozenset(int(s) for s in _USABLE)
_SOLVED = int(osqp.SolverStatus.OSQP_SOLVED)
_TIME_LIMIT = int(osqp.SolverStatus.OSQP_TIME_LIMIT_REACHED)
"""The status values as plain integers (an ``IntEnum`` comparison costs several times an
``int``'s, every cycle)."""


RHO = 0.03
"""OSQP's initial step size (the states are scaled to O(1), see :mod:`truckd.control.qp`),
adapted every 50 iterations when OSQP's estimate differs by more than 2x.  Measured on
``truckd sim``'s scenarios (estimator noise, 100 Hz), iterations p50/p99 against OSQP's
default rho 0.1 with tolerance 5: follow 25/30 (55/85), stop-and-go 40/155 (65/165),
lead-brake 25/130 (45/165), cut-in 30/45 (25/85).  A fixed rho 0.01 was as fast on smooth
sequences but slower at rest (p99 270) and left some cold starts at eps 1e-6 past 50,000
iterations; adapting every 25 iterations made rho oscillate (see docs/controller.md)."""

RHO_BLOCKED = 1.0
"""The initial rho of the move-blocked, condensed QP.  On the stop-and-go sequence at N = 40
(8 blocks, 137 rows), iterations p50/p99: rho 1.0 30/50; 0.3 30/200; 0.1 30/178; 0.03 30/210
(the long tail is braking to rest with the minimum-gap and rate rows active).  On the 85-row
QP over ten trucks and six scenarios (``benchmarks/mpc_settings.py``, 84 000 QPs), rho 0.03
with alpha 1.8 and an update tolerance of 5 halves the iterations (mean 17.7 -> 9.3, p99 65 ->
20, max 315 -> 205) but takes 15 % more on the recorded follow replay (9.36 -> 10.74: past
the 300 k instructions a cycle), and its rounding lifts a drawn ten-truck platoon's
spacing-error ratio to 1.004 (0.982 here, 0.987 at the exact optimum): not adopted
(docs/controller.md)."""

ALPHA_BLOCKED = 1.6
"""OSQP's relaxation of the move-blocked QP (OSQP's default, as the sparse QP's)."""

RHO_TOLERANCE_BLOCKED = 2.0
"""How far OSQP's rho estimate must move (a factor) before the move-blocked QP's rho is
updated (each update refactors the KKT matrix)."""


CHECK_DUALGAP_BLOCKED = 0
"""OSQP 1.x's duality-gap termination test, off for the move-blocked QP: OSQP stops on its
primal and dual residuals alone (as OSQP 0.6 did), and the compiled cycle's generated solver
then leaves out the objective and duality gap it would compute at every check
(``tools/generate_mpc_solver.py``).  Iterations mean / p99: the recorded replay 20.35 / 35
with it and without (the gap never decided there); the stop-and-go sequence at N = 40
24.0 / 50 -> 22.7 / 40, first moves within 0.27 mV of an eps 1e-9 solve in both."""


def osqp_settings(cfg: ControlConfig) -> dict[str, float | int | bool]:
    """The OSQP settings of the controller (the benchmark's cold solver uses them too)."""
    return {
        "verbose": False,
        "eps_abs": cfg.eps,
        "eps_rel": cfg.eps,
        "max_iter": cfg.max_iter,
        "time_limit": cfg.time_budget_s,
        "warm_starting": True,
        "polishing": False,
        "check_termination": 5,
        "rho": RHO if cfg.move_blocks == 0 else RHO_BLOCKED,
        "alpha": 1.6 if cfg.move_blocks == 0 else ALPHA_BLOCKED,
        "adaptive_rho_interval": 50,
        "adaptive_rho_tolerance": 2.0 if cfg.move_blocks == 0 else RHO_TOLERANCE_BLOCKED,
        "check_dualgap": 1 if cfg.move_blocks == 0 else CHECK_DUALGAP_BLOCKED,
    }


def codegen_settings(cfg: ControlConfig) -> dict[str, float | int | bool]:
    """:func:`osqp_settings` for OSQP's code generation (the time limit, which depends on
    the configuration, is set at start-up with the tolerance and the iteration limit)."""
    return osqp_settings(cfg)


class MpcSolver:
    """The MPC QP with a persistent, warm-started OSQP solver per mode.

    ``compiled``: run the per-cycle numerics of the move-blocked QP compiled
    (:mod:`truckd.control.ccycle`) when the library is built and fits this QP; the
    Python path otherwise (:attr:`backend` says which and why)."""

    def __init__(self, model: ControlModel, cfg: ControlConfig, compiled: bool = True) -> None:
        self.cfg = cfg
        self.qp = QpBuilder(model, cfg)
        self._solvers: dict[str, osqp.OSQP] = {}
        lay = self.qp.lay
        self.condensed: CondensedQp | None = None
        """The move-blocked QP actually solved (None: the sparse one)."""
        if cfg.move_blocks > 0:
            tau_m = model.params.mechanical_time_constant
            longest = max_block_steps(tau_m, cfg.period, cfg.block_tau_fraction)
            self.condensed = CondensedQp(self.qp, block_lengths(lay.N, cfg.move_blocks, longest))
            nv, nc = self.condensed.nw, self.condensed.m
        else:
            nv, nc = lay.nz, lay.m
        # Per-cycle work arrays (the vectors are copied into OSQP by its update); the
        # condensed QP writes its own (one product fills all three).
        if self.condensed is None:
            self._q, self._lo, self._hi = np.empty(nv), np.empty(nc), np.empty(nc)
        else:
            c = self.condensed
            self._q, self._lo, self._hi = c.q_view, c.lo_view, c.hi_view
        self._xw = np.empty(nv)
        self._yw = np.empty(nc)
        self._x_cold = np.zeros(nv)
        self._y_cold = np.zeros(nc)
        zero_inp = QpInputs(
            x0=np.zeros(3),
            u_prev=0.0,
            v_lead=np.zeros(lay.N),
            lead=False,
            v_ref=0.0,
            v_cap=cfg.v_max,
            u_lo=-cfg.u_max,
            u_hi=cfg.u_max,
        )
        self.zero_inputs = zero_inp
        """The inputs the solvers are set up with (all zero, no lead, the widest bounds)."""
        cq = self.condensed
        for mode in MODES:
            self._vectors_into(mode, zero_inp)
            s = osqp.OSQP()
            if cq is None:
                p_triu, a = sp.triu(self.qp.P[mode], format="csc"), self.qp.A
            else:
                p_triu, a = cq.p_triu(mode), cq.A
            s.setup(p_triu, self._q, a, self._lo, self._hi, **osqp_settings(cfg))
            self._solvers[mode] = s
        self._rho0 = float(osqp_settings(cfg)["rho"])
        """The step size every solver starts with (OSQP adapts it while solving)."""
        self._last: tuple[Vec, list[float] | Vec] | None = None
        """The last accepted solution: OSQP's primal vector and (condensed) the inputs it
        was solved for."""
        self._last_v: Vec | None = None
        self._last_plan: Vec | None = None
        self._warm: tuple[Vec, Vec] | None = None
        self.inaccurate = 0
        """Solutions used although OSQP reported ``solved inaccurate``."""
        self._cc: ccycle.CompiledCycle | None = None
        why = "the sparse QP (move_blocks 0) has no compiled path"
        if not compiled:
            why = "compiled path not requested"
        elif cq is not None:
            self._cc, why = self._compiled_cycle(cq)
        self.backend = "compiled" if self._cc is not None else f"python ({why})"
        """Which path solves: ``compiled`` (OSQP's generated solver and the fill and plan
        in C, one call per cycle) or ``python (why)``; logged at start-up."""

    def _compiled_cycle(self, cq: CondensedQp) -> tuple[ccycle.CompiledCycle | None, str]:
        """The compiled cycle set up with this truck's matrices and settings, or why not."""
        cc, why = ccycle.claim(self, cq)
        if cc is None:
            return None, why
        st = osqp_settings(self.cfg)
        for k, mode in enumerate(MODES):
            self._vectors_into(mode, self.zero_inputs)  # as the Python solvers were set up
            flag = cc.setup(
                k,
                cq.p_triu(mode).data,
                cq.A.data,
                float(st["eps_abs"]),
                int(st["max_iter"]),
                int(st["check_termination"]),
                float(st["time_limit"]),
                self._rho0,
                float(st["alpha"]),
                int(st["adaptive_rho_interval"]),
                float(st["adaptive_rho_tolerance"]),
            )
            if flag != 0:
                ccycle.release(cc.instance, cc.claim_number)
                return None, f"the generated {mode} solver refused this truck's matrices ({flag})"
        return cc, ""

    @property
    def horizon(self) -> int:
        """Steps in the horizon."""
        return self.qp.lay.N

    @property
    def last_solution(self) -> Vec | None:
        """The last accepted solution in the sparse layout (see
        :class:`~truckd.control.qp.Layout`), a new array; None after a failure or a
        reset.  Condensed: expanded now, from the blocked solution and its inputs."""
        if self._last is None:
            return None
        x, inputs = self._last
        cq = self.condensed
        return x.copy() if cq is None else cq.expand_filled(x, inputs)

    @property
    def last_speeds(self) -> Vec | None:
        """The predicted speeds ``v_0 .. v_N`` (m/s) of the last accepted solution."""
        return self._last_v

    @property
    def last_plan(self) -> Vec | None:
        """The plan of :attr:`last_speeds` as the compiled cycle made it: the speeds
        clipped at 0, then their accelerations over the period (``2 (N + 1)`` values,
        m/s and m/s^2, the same as :func:`~truckd.control.platoon.plan_of_array`'s);
        None when the last accepted solution came from the Python path, or none."""
        return self._last_plan

    @property
    def has_warm_start(self) -> bool:
        """Whether the next solve is warm started (else it starts from zero)."""
        return self._warm is not None

    def _vectors_into(self, mode: str, inp: QpInputs) -> None:
        if self.condensed is None:
            self.qp.vectors_into(mode, inp, self._q, self._lo, self._hi)
        else:
            self.condensed.fill(mode, inp)

    def reset(self) -> None:
        """Forget the previous solution (no warm start next time)."""
        self._last = None
        self._last_v = None
        self._last_plan = None
        self._warm = None

    def restart(self) -> None:
        """:meth:`reset`, and each solver's step size rho back to where it started (OSQP
        adapts it while solving; a new rho refactors the KKT matrix, so not every cycle):
        the next solve is a new solver's."""
        self.reset()
        for s in self._solvers.values():
            s._solver.update_rho(self._rho0)
        if self._cc is not None:
            for k in range(len(MODES)):
                self._cc.update_rho(k, self._rho0)

    def set_max_iter(self, max_iter: int) -> None:
        """OSQP's iteration limit of every mode's solver, in either path (tests: a solver
        that stops short fails as OSQP does at its limit)."""
        for k, s in enumerate(self._solvers.values()):
            s.update_settings(max_iter=max_iter)
            if self._cc is not None:
                self._cc.set_max_iter(k, max_iter)

    def solve(self, mode: str, inp: QpInputs, warm: bool = True) -> MpcResult:
        """Update the vectors, warm start, solve, check.  Never raises on solver trouble."""
        if self._cc is not None:
            return self._solve_compiled(mode, inp, warm)
        s = self._solvers[mode]
        qp, cq = self.qp, self.condensed
        # Every input finite and physical (qp.inputs_ok): the condensed QP's fill checks
        # the vector it gathers them into.
        if cq is not None:
            finite = cq.fill(mode, inp)
        else:
            scalars = (inp.u_prev, inp.v_ref, inp.v_cap, inp.u_lo, inp.u_hi)
            finite = inputs_ok([*map(float, (*scalars, *inp.x0, *inp.v_lead))])
        if not finite:
            return MpcResult(False, math.nan, "non-finite-input", 0, 0.0)
        if cq is None:
            qp.vectors_into(mode, inp, self._q, self._lo, self._hi)
        # The binding directly (osqp.OSQP.update and .solve wrap it with copies, clipping
        # and a namespace of every info field: a quarter of the cycle's Python time).  Our
        # infinity (qp.INF) is OSQP's, so nothing needs clipping.
        ext = s._solver
        try:
            ext.update_data_vec(q=self._q, l=self._lo, u=self._hi)
            if warm and self._warm is not None and cq is not None:
                # Blocks do not shift by one step: the previous solution as it is.
                ext.warm_start(self._warm[0], self._warm[1])
            elif warm and self._warm is not None:
                ext.warm_start(
                    qp.shift(self._warm[0], self._xw), qp.shift_dual(self._warm[1], self._yw)
                )
            else:  # cold: from zero, not from whatever this mode's solver saw last
                ext.warm_start(self._x_cold, self._y_cold)
            ext.solve()
        except (ValueError, RuntimeError, osqp.OSQPException) as exc:  # defensive
            self.reset()
            return MpcResult(False, math.nan, f"error: {exc}", 0, 0.0)
        info = ext.info
        status_val = info.status_val
        run_time = float(info.run_time)
        iters = int(info.iter)
        # The binding hands out a new float64 array on every access of ``x``/``y`` (a copy
        # of the solver's memory, test_mpc_condensed checks it): kept as they are.
        sol = ext.solution
        z: Vec = sol.x
        y: Vec = sol.y
        # Python's sum (no numpy warning on an overflow; tolist runs every cycle anyway):
        # a numpy reduction would be one more code path, cold after the period's sleep.
        finite = math.isfinite(sum(z.tolist()) + sum(y.tolist()))
        if status_val not in _USABLE or not finite:
            status = str(info.status)
            # Out of time: the unfinished iterate still warm starts the next cycle (a cold
            # start is slower, and overruns would cascade).  Any other failure: the next
            # solve starts cold, a warm start that led nowhere is not offered again.
            if status_val == osqp.SolverStatus.OSQP_TIME_LIMIT_REACHED and finite:
                self._warm = (z, y)
            else:
                self.reset()
            return MpcResult(False, math.nan, status if finite else "non-finite", iters, run_time)
        self._warm = (z, y)
        if run_time > self.cfg.time_budget_s:
            return MpcResult(False, math.nan, "overrun", iters, run_time)
        if cq is not None:
            u, v = cq.plan(z)
            self._last = (z, cq.filled)
        else:
            u0 = qp.lay.u0
            u, v = z[u0 : u0 + qp.lay.N], qp.speeds(z)
            self._last = (z, [])
        self._last_v = v
        self._last_plan = None
        if status_val != osqp.SolverStatus.OSQP_SOLVED:
            self.inaccurate += 1
        return MpcResult(True, float(u[0]), str(info.status), iters, run_time, u, v)

    def _solve_compiled(self, mode: str, inp: QpInputs, warm: bool) -> MpcResult:
        """:meth:`solve` through the compiled cycle: the same steps and outcomes.  Every
        cycle: the inputs go into the library's vector by one ``struct`` call (a numpy
        slice assignment from a list inspects every element first), the outcome comes out
        as Python numbers, the statuses are compared as plain integers."""
        cc, cq = self._cc, self.condensed
        assert cc is not None and cq is not None
        values = cq.gather(inp)
        if values is None:
            return MpcResult(False, math.nan, "non-finite-input", 0, 0.0)
        cc.put_values(values)
        v_lead = values[cq.n_fixed_inputs :]
        one_speed = v_lead.count(v_lead[0]) == len(v_lead)
        status_val = cc.cycle(
            _MODE_INDEX[mode], inp.lead, one_speed, warm and self._warm is not None
        )
        return self.compiled_outcome(status_val, values)

    @property
    def compiled_cycle(self) -> ccycle.CompiledCycle | None:
        """The compiled cycle this solver runs (None: the Python path)."""
        return self._cc

    def compiled_outcome(self, status_val: int, values: list[float] | None = None) -> MpcResult:
        """The outcome of the compiled cycle just run (by :meth:`solve`, or by the
        controller's compiled numerics, :mod:`truckd.control.cnumerics`, which returns
        :data:`~truckd.control.ccycle.BAD_INPUT` for inputs refused before the solve):
        the same warm start, plan and counters as :meth:`solve`.  ``values``: the cycle's
        inputs (None: read back from the library's vector)."""
        cc = self._cc
        assert cc is not None
        if status_val == ccycle.BAD_INPUT:
            return MpcResult(False, math.nan, "non-finite-input", 0, 0.0)
        if status_val < 0:  # defensive: the call itself refused
            self.reset()
            return MpcResult(False, math.nan, f"error: compiled cycle {status_val}", 0, 0.0)
        kept: list[float] | Vec = cc.values.copy() if values is None else values
        if values is None:  # the compiled numerics gathered them (kept as an array)
            assert self.condensed is not None
            self.condensed.filled = kept
        _, iters_f, run_time, finite_f = cc.info.tolist()
        iters, finite = math.trunc(iters_f), finite_f == 1.0  # (int() of a whole float)
        z, y = cc.solution()
        if status_val not in _USABLE_VALUES or not finite:
            status = ccycle.status_text(status_val)
            if status_val == _TIME_LIMIT and finite:
                self._keep_compiled(z, y)
            else:
                self.reset()
            return MpcResult(False, math.nan, status if finite else "non-finite", iters, run_time)
        if run_time > self.cfg.time_budget_s:
            self._keep_compiled(z, y)
            return MpcResult(False, math.nan, "overrun", iters, run_time)
        self._last = (z, kept)
        self._keep_compiled(z, y)
        u, v = cc.u.copy(), cc.v.copy()
        self._last_v = v
        self._last_plan = cc.plan.copy() if cc.plan_bound else None
        if status_val != _SOLVED:
            self.inaccurate += 1
        status = ccycle.STATUS_TEXT[status_val]  # a usable status: status_text's own
        return MpcResult(True, u.item(0), status, iters, run_time, u, v)

    def _keep_compiled(self, z: Vec, y: Vec) -> None:
        """The compiled cycle's solution as the next warm start (its arrays then stay as
        they are until the next one is kept: the last accepted solution is copied first)."""
        assert self._cc is not None
        if self._last is not None and self._last[0] is not z:
            self._last = (self._last[0].copy(), self._last[1])
        self._cc.keep()
        self._warm = (z, y)
