"""Warm-started OSQP MPC: set up once per mode, vectors updated every cycle.

One OSQP instance per cost mode (``follow``, ``cruise``) is set up at construction;
each cycle only ``q``, ``l``, ``u`` are updated and the solver is warm started from the
previous solution shifted one step.  The status is checked every cycle: anything but
``solved`` (or ``solved inaccurate``, counted) within the time budget (OSQP's
``time_limit``; the solver's own run time is checked as well) is a failure the caller
must handle (see
:class:`truckd.control.controller.Controller`).  No clock here: times come from OSQP.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import osqp
import scipy.sparse as sp

from truckd.control.config import ControlConfig
from truckd.control.qp import MODES, ControlModel, QpBuilder, QpInputs, Vec


@dataclass(frozen=True)
class MpcResult:
    """Outcome of one solve.

    ``ok`` solved within budget with a finite solution; ``u0`` first move (V, NaN when
    not ok); ``status`` OSQP's status text (or ``"overrun"``/``"non-finite"``);
    ``iterations``; ``run_time_s`` OSQP's own measured update+solve time (s).
    """

    ok: bool
    u0: float
    status: str
    iterations: int
    run_time_s: float
    z: Vec | None


_USABLE = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
"""Statuses whose solution is used.  ``solved inaccurate`` met OSQP's relaxed (10x)
tolerances at the iteration limit: good to about 1e-3 V, counted in ``inaccurate``."""


class MpcSolver:
    """The MPC QP with a persistent, warm-started OSQP solver per mode."""

    def __init__(self, model: ControlModel, cfg: ControlConfig) -> None:
        self.cfg = cfg
        self.qp = QpBuilder(model, cfg)
        self._solvers: dict[str, osqp.OSQP] = {}
        lay = self.qp.lay
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
        for mode in MODES:
            q, lo, hi = self.qp.vectors(mode, zero_inp)
            s = osqp.OSQP()
            s.setup(
                sp.triu(self.qp.P[mode], format="csc"),
                q,
                self.qp.A,
                lo,
                hi,
                verbose=False,
                eps_abs=cfg.eps,
                eps_rel=cfg.eps,
                max_iter=cfg.max_iter,
                time_limit=cfg.time_budget_s,
                warm_starting=True,
                polishing=False,
                check_termination=5,
                adaptive_rho_interval=50,
            )
            self._solvers[mode] = s
        self._last_z: Vec | None = None
        self._warm: tuple[Vec, Vec] | None = None
        self.inaccurate = 0
        """Solutions used although OSQP reported ``solved inaccurate``."""

    @property
    def horizon(self) -> int:
        """Steps in the horizon."""
        return self.qp.lay.N

    @property
    def last_solution(self) -> Vec | None:
        """The last accepted solution vector (see :class:`~truckd.control.qp.Layout`)."""
        return self._last_z

    @property
    def has_warm_start(self) -> bool:
        """Whether the next solve is warm started (else it starts from zero)."""
        return self._warm is not None

    def reset(self) -> None:
        """Forget the previous solution (no warm start next time)."""
        self._last_z = None
        self._warm = None

    def solve(self, mode: str, inp: QpInputs, warm: bool = True) -> MpcResult:
        """Update the vectors, warm start, solve, check.  Never raises on solver trouble."""
        s = self._solvers[mode]
        scalars = (inp.u_prev, inp.v_ref, inp.v_cap, inp.u_lo, inp.u_hi)
        if not (
            all(math.isfinite(x) for x in scalars)
            and np.isfinite(inp.x0).all()
            and np.isfinite(inp.v_lead).all()
        ):
            return MpcResult(False, math.nan, "non-finite-input", 0, 0.0, None)
        q, lo, hi = self.qp.vectors(mode, inp)
        s.update(q=q, l=lo, u=hi)
        if warm and self._warm is not None:
            s.warm_start(x=self.qp.shift(self._warm[0]), y=self.qp.shift_dual(self._warm[1]))
        else:  # cold: from zero, not from whatever this mode's solver saw last
            s.warm_start(x=np.zeros(self.qp.lay.nz), y=np.zeros(self.qp.lay.m))
        try:
            res = s.solve(raise_error=False)
        except (ValueError, osqp.OSQPException) as exc:  # defensive: bindings may raise
            self.reset()
            return MpcResult(False, math.nan, f"error: {exc}", 0, 0.0, None)
        info = res.info
        run_time = float(getattr(info, "run_time", 0.0))
        iters = int(info.iter)
        status = str(info.status)
        z = np.array(res.x, dtype=float)
        y = np.array(res.y, dtype=float)
        finite = bool(np.isfinite(z).all() and np.isfinite(y).all())
        timed_out = info.status_val == osqp.SolverStatus.OSQP_TIME_LIMIT_REACHED
        if info.status_val not in _USABLE or not finite:
            # Out of time: the unfinished iterate still warm starts the next cycle (a cold
            # start is slower, and overruns would cascade).  Any other failure: the next
            # solve starts cold, a warm start that led nowhere is not offered again.
            if timed_out and finite:
                self._warm = (z, y)
            else:
                self.reset()
            return MpcResult(
                False, math.nan, status if finite else "non-finite", iters, run_time, None
            )
        self._warm = (z, y)
        if run_time > self.cfg.time_budget_s:
            return MpcResult(False, math.nan, "overrun", iters, run_time, z)
        self._last_z = z
        if info.status_val != osqp.SolverStatus.OSQP_SOLVED:
            self.inaccurate += 1
        return MpcResult(True, self.qp.first_move(z), status, iters, run_time, z)
