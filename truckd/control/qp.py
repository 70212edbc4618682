"""The MPC's quadratic program: prediction model, cost, constraints (pure numerics).

Prediction model (friction-free; the feedforward cancels friction): states
``x = [e, v, d]`` (``e = R_m i`` the armature current as its resistive drop, V; speed
m/s; gap m), inputs the armature voltage u
(V) and the lead speed ``v_lead`` (m/s), continuous time

    L_m di/dt = u - R_m i - K_v v / rho
    dv/dt     = rho (K_T i - b v / rho) / J_S          (rho = r_w / (n_g n_fd))
    dd/dt     = v_lead - v

derived from the model's own state space (:func:`truckd.model.linear.state_space`, one
source of the physics: only the change of coordinates ``[i, omega_m] -> [R_m i, v]`` and
the gap row are added here) and discretised exactly (zero-order hold over the control
period, :func:`truckd.model.linear.zoh`).
The electrical pole (``L_m/R_m`` about 0.5 ms) is kept: the exact ZOH handles the
stiffness, and the current state costs three variables per step, so no reduction is needed.

Decision vector ``z = [x_0 .. x_N, u_0 .. u_{N-1}, sg, sv]`` with one slack for the
minimum gap and one for the speed limits, shared by every step (they penalise the worst
violation over the horizon; per-step slacks made each OSQP iteration 30% slower).  Cost (OSQP form
``1/2 z'Pz + q'z``), per mode:

* ``follow``: ``sum_k q_gap (d_k - h v_k - d_0)^2 + q_rel (v_k - v_lead_k)^2``;
* ``cruise``: ``sum_k q_cruise (v_k - v_ref)^2``;
* both: ``r_du (u_k - u_{k-1})^2`` (``u_{-1}`` the previous command), a terminal cost
  from the discrete algebraic Riccati equation of the unconstrained problem (so the
  finite horizon matches the infinite one when no constraint is active), and
  ``slack_linear s + slack_quadratic s^2`` on every slack.

Constraints: dynamics; ``x_0`` = the estimate; ``u_lo <= u_k <= u_hi``; ``|u_k - u_{k-1}|
<= du_max dt``; ``d_k + sg >= d_min`` (only with a lead); ``v_k - sv <= v_cap``,
``v_k + sv >= 0`` (no reversing); slacks >= 0.  Every constraint on states is soft, the
hard ones (input bounds, rate) are satisfied by holding the previous command, so the QP is
never infeasible.  Only ``q``, ``l`` and ``u`` change from cycle to cycle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from truckd.control.config import ControlConfig
from truckd.control.frozen import fast_init
from truckd.control.riccati import solve_dare
from truckd.model.effects import Effects
from truckd.model.linear import state_space, zoh
from truckd.model.params import VehicleParams

Vec = NDArray[np.float64]
Floats = Sequence[float] | Vec
"""Values as a list of floats or an array."""
INF = 1e30
"""Unbounded constraint side (OSQP clips at its own infinity)."""

INPUT_LIMIT = 1e9
"""The QP's inputs (volts, metres, metres per second) summed in magnitude stay below this,
far beyond anything physical on a model truck; more, or a NaN or an infinity, is refused
(:func:`inputs_ok`) before it reaches the solver or overflows a product."""


def inputs_ok(values: list[float]) -> bool:
    """Every value finite and their magnitudes summing below :data:`INPUT_LIMIT` (a NaN
    makes the sum NaN and the comparison false; a sum of Python floats overflows to inf
    without a warning, numpy scalars would warn: pass Python floats)."""
    return sum(map(abs, values)) < INPUT_LIMIT


MODES: tuple[str, ...] = ("follow", "cruise")
NX = 3
I_CUR, I_V, I_D = 0, 1, 2


@dataclass(frozen=True)
class ControlModel:
    """What the controller believes about the truck: seed parameters plus known effects."""

    params: VehicleParams
    effects: Effects = field(default_factory=Effects)


@dataclass(frozen=True)
class Prediction:
    """Discrete prediction model ``x+ = Ad x + bu u + bl v_lead`` over ``dt`` (s)."""

    Ad: Vec
    bu: Vec
    bl: Vec
    dt: float


def coordinates(p: VehicleParams) -> Vec:
    """``T`` with ``[e, v] = T [i, omega_m]``: the model's states as the MPC's
    (``e = R_m i`` in V, ``v = rho omega_m`` in m/s)."""
    return np.diag([p.R_m, p.ratio])


def continuous_model(model: ControlModel) -> tuple[Vec, Vec]:
    """The model's linear part (with the known viscous friction) in continuous time, in
    the MPC's coordinates: ``(A, B)`` of ``d/dt [e, v, d] = A [e, v, d] + B [u, v_lead]``,
    the gap ``dd/dt = v_lead - v`` appended."""
    p = model.params
    ss = state_space(p, model.effects.viscous_friction)
    # States [e = R_m i (V), v, d]: the current as its resistive voltage drop, so that
    # every state and the input are O(1) in their units (OSQP converges 3x faster).
    t = coordinates(p)
    t_inv = np.diag(1.0 / np.diag(t))
    a = np.zeros((NX, NX))
    a[:2, :2] = t @ ss.A @ t_inv
    a[I_D, :2] = -(ss.C @ t_inv)[0]
    bmat = np.zeros((NX, 2))
    bmat[:2, 0] = (t @ ss.B)[:, 0]
    bmat[I_D, 1] = 1.0
    return a, bmat


def prediction_model(model: ControlModel, dt: float) -> Prediction:
    """Exact ZOH of :func:`continuous_model` over ``dt`` (s)."""
    ad, bd = zoh(*continuous_model(model), dt)
    return Prediction(Ad=ad, bu=bd[:, 0].copy(), bl=bd[:, 1].copy(), dt=dt)


def accel_row(model: ControlModel) -> Vec:
    """The truck's acceleration (m/s^2) as a row on the MPC's state ``[R_m i, v, d]``: the
    linear model's ``dv/dt`` (the input acts on the current only, so no input term)."""
    row: Vec = continuous_model(model)[0][I_V].copy()
    return row


def rel_speed_row(cfg: ControlConfig, accel: Vec) -> Vec:
    """The follow term's speed ``v + T a`` (m/s) as a row on the MPC's state, ``T`` the
    configuration's ``rel_speed_lookahead`` (s) and ``accel`` :func:`accel_row`."""
    row = cfg.rel_speed_lookahead * np.asarray(accel, dtype=float)
    row[I_V] += 1.0
    return row


def steady_state(model: ControlModel, v: float) -> tuple[float, float]:
    """Friction-free steady state at speed v (m/s): ``(R_m i (V), voltage (V))``."""
    p = model.params
    omega = p.omega(v)
    e = p.R_m * model.effects.viscous_friction * omega / p.K_T
    return e, e + p.K_v * omega


def stage_weight(cfg: ControlConfig, mode: str, rel_row: Vec | None = None) -> Vec:
    """State weight matrix Q (3x3) of one mode, in error coordinates; ``rel_row`` the
    follow term's row (:func:`rel_speed_row`; None: the speed alone)."""
    q = np.zeros((NX, NX))
    if mode == "follow":
        c = np.array([0.0, -cfg.time_headway, 1.0])
        q += cfg.q_gap * np.outer(c, c)
        if rel_row is None:
            q[I_V, I_V] += cfg.q_rel_speed
        else:
            q += cfg.q_rel_speed * np.outer(rel_row, rel_row)
    elif mode == "cruise":
        q[I_V, I_V] = cfg.q_cruise
    else:
        raise ValueError(f"unknown MPC mode {mode!r}")
    return q


def terminal_weight(pred: Prediction, q: Vec, r_du: float) -> Vec:
    """DARE solution (4x4) for ``xi = [x; u_prev]`` with input ``du``.

    States no weight reaches (the gap while cruising) are left out of the Riccati
    equation and get zero terminal weight.
    """
    a = np.zeros((NX + 1, NX + 1))
    a[:NX, :NX] = pred.Ad
    a[:NX, NX] = pred.bu
    a[NX, NX] = 1.0
    b = np.zeros((NX + 1, 1))
    b[:NX, 0] = pred.bu
    b[NX, 0] = 1.0
    qa = np.zeros((NX + 1, NX + 1))
    qa[:NX, :NX] = q
    keep = [I_CUR, I_V, NX] if q[I_D, I_D] == 0.0 else [I_CUR, I_V, I_D, NX]
    ix = np.ix_(keep, keep)
    sub = solve_dare(a[ix], b[keep], qa[ix], np.array([[r_du]]))
    out = np.zeros((NX + 1, NX + 1))
    out[ix] = 0.5 * (sub + sub.T)
    return out


class Layout:
    """Index bookkeeping of the decision vector and the constraint rows."""

    def __init__(self, n: int) -> None:
        self.N = n
        self.nz = NX * (n + 1) + n + 2
        self.u0 = NX * (n + 1)
        self.sg0 = self.u0 + n
        self.sv0 = self.sg0 + 1
        # Constraint row blocks.
        self.r_init = 0
        self.r_dyn = NX
        self.r_u = self.r_dyn + NX * n
        self.r_du = self.r_u + n
        self.r_gap = self.r_du + (n - 1)
        self.r_vhi = self.r_gap + n
        self.r_vlo = self.r_vhi + n
        self.r_slack = self.r_vlo + n
        self.m = self.r_slack + 2

    def x(self, k: int) -> int:
        """Index of ``x_k[0]``."""
        return NX * k


def constraint_matrix(pred: Prediction, lay: Layout) -> sp.csc_matrix:
    """The constant constraint matrix A (rows as in :class:`Layout`)."""
    n = lay.N
    a = sp.lil_matrix((lay.m, lay.nz))
    for j in range(NX):
        a[lay.r_init + j, j] = 1.0
    for k in range(n):
        r = lay.r_dyn + NX * k
        for i in range(NX):
            for j in range(NX):
                if pred.Ad[i, j] != 0.0:
                    a[r + i, lay.x(k) + j] = pred.Ad[i, j]
            a[r + i, lay.x(k + 1) + i] = -1.0
            if pred.bu[i] != 0.0:
                a[r + i, lay.u0 + k] = pred.bu[i]
        a[lay.r_u + k, lay.u0 + k] = 1.0
        if k >= 1:
            a[lay.r_du + k - 1, lay.u0 + k] = 1.0
            a[lay.r_du + k - 1, lay.u0 + k - 1] = -1.0
        a[lay.r_gap + k, lay.x(k + 1) + I_D] = 1.0
        a[lay.r_gap + k, lay.sg0] = 1.0
        a[lay.r_vhi + k, lay.x(k + 1) + I_V] = 1.0
        a[lay.r_vhi + k, lay.sv0] = -1.0
        a[lay.r_vlo + k, lay.x(k + 1) + I_V] = 1.0
        a[lay.r_vlo + k, lay.sv0] = 1.0
    a[lay.r_slack, lay.sg0] = 1.0
    a[lay.r_slack + 1, lay.sv0] = 1.0
    return sp.csc_matrix(a)


def cost_matrix(cfg: ControlConfig, lay: Layout, q: Vec, pf: Vec) -> sp.csc_matrix:
    """The constant, symmetric cost matrix P of one mode (full, not triangular)."""
    n = lay.N
    p = sp.lil_matrix((lay.nz, lay.nz))
    for k in range(1, n):
        s = lay.x(k)
        for i in range(NX):
            for j in range(NX):
                if q[i, j] != 0.0:
                    p[s + i, s + j] += 2.0 * q[i, j]
    # Rate penalty on u_0 - u_prev and u_k - u_{k-1}.
    r = cfg.r_du
    for k in range(n):
        p[lay.u0 + k, lay.u0 + k] += 2.0 * r
        if k >= 1:
            p[lay.u0 + k - 1, lay.u0 + k - 1] += 2.0 * r
            p[lay.u0 + k, lay.u0 + k - 1] += -2.0 * r
            p[lay.u0 + k - 1, lay.u0 + k] += -2.0 * r
    # Terminal cost on [x_N, u_{N-1}].
    idx = [lay.x(n) + j for j in range(NX)] + [lay.u0 + n - 1]
    for a_, ia in enumerate(idx):
        for b_, ib in enumerate(idx):
            if pf[a_, b_] != 0.0:
                p[ia, ib] += 2.0 * pf[a_, b_]
    for j in (lay.sg0, lay.sv0):
        p[j, j] += 2.0 * cfg.slack_quadratic
    return sp.csc_matrix(p)


@fast_init
@dataclass(frozen=True)
class QpInputs:
    """What changes from cycle to cycle.

    ``x0`` = [R_m i (V), v (m/s), d (m)]; ``u_prev`` the previous command's MPC part (V);
    ``v_lead`` lead speed over the horizon (N values, m/s); ``lead`` whether a lead is
    tracked (enables the minimum gap); ``v_ref`` cruise speed (m/s); ``v_cap`` speed limit
    (m/s); ``u_lo``/``u_hi`` bounds on the MPC part of the voltage (V).  ``x0`` and
    ``v_lead`` are lists of floats or arrays (the controller passes lists: the condensed
    QP gathers its inputs without a numpy call).
    """

    x0: Floats
    u_prev: float
    v_lead: Floats
    lead: bool
    v_ref: float
    v_cap: float
    u_lo: float
    u_hi: float


class QpBuilder:
    """Builds P and A once per mode, and q, l, u every cycle."""

    def __init__(self, model: ControlModel, cfg: ControlConfig) -> None:
        self.model = model
        self.cfg = cfg
        self.pred = prediction_model(model, cfg.period)
        self.lay = Layout(cfg.horizon)
        self.A = constraint_matrix(self.pred, self.lay)
        self.rel_row = (
            rel_speed_row(cfg, accel_row(model)) if cfg.rel_speed_lookahead > 0.0 else None
        )
        """The follow term's row on the state (``v + T a``, :func:`rel_speed_row`); None
        with ``T`` = 0: the speed alone (the relative speed)."""
        self.Q = {m: stage_weight(cfg, m, self.rel_row) for m in MODES}
        self.Pf = {m: terminal_weight(self.pred, self.Q[m], cfg.r_du) for m in MODES}
        self.P = {m: cost_matrix(cfg, self.lay, self.Q[m], self.Pf[m]) for m in MODES}
        self._templates()

    def _templates(self) -> None:
        """Constant parts of q, l, u (the per-cycle parts are written over copies), and the
        index arrays of the per-cycle updates and of the warm-start shift."""
        cfg, lay, n = self.cfg, self.lay, self.lay.N
        self._ks_v = NX * np.arange(1, n) + I_V
        # The terminal cost's linear term is -2 Pf [e_ss, v_end, d_end, u_ss]; the steady
        # state is linear in v_end, so it is a constant plus v_end times a slope.
        e1, u1 = steady_state(self.model, 1.0)
        self._term_idx = np.array([lay.x(n) + j for j in range(NX)] + [lay.u0 + n - 1])
        self._q0: dict[str, Vec] = {}
        self._term_slope: dict[str, Vec] = {}
        for mode in MODES:
            q = np.zeros(lay.nz)
            if mode == "follow":
                # q_gap (c'x - d_0)^2 with c = [0, -h, 1]: the d_0 cross term.
                g = -2.0 * cfg.q_gap * cfg.d_0
                q[self._ks_v] += g * (-cfg.time_headway)
                q[self._ks_v + (I_D - I_V)] += g
                end0 = np.array([0.0, 0.0, cfg.d_0, 0.0])
                slope = np.array([e1, 1.0, cfg.time_headway, u1])
            else:
                end0 = np.zeros(NX + 1)
                slope = np.array([e1, 1.0, 0.0, u1])
            q[self._term_idx] += -2.0 * self.Pf[mode] @ end0
            q[lay.sg0 :] += cfg.slack_linear
            self._q0[mode] = q
            self._term_slope[mode] = -2.0 * self.Pf[mode] @ slope
        lo = np.empty(lay.m)
        hi = np.empty(lay.m)
        du = cfg.du_max * cfg.period
        lo[lay.r_du : lay.r_gap] = -du
        hi[lay.r_du : lay.r_gap] = du
        hi[lay.r_gap : lay.r_vhi] = INF
        lo[lay.r_vhi : lay.r_vlo] = -INF
        lo[lay.r_vlo : lay.r_slack] = 0.0
        hi[lay.r_vlo : lay.r_slack] = INF
        lo[lay.r_slack :] = 0.0
        hi[lay.r_slack :] = INF
        self._lo0, self._hi0 = lo, hi
        self._neg_bl = -self.pred.bl
        # Warm-start shifts as one gather each: source index of every output entry.
        zi = np.arange(lay.nz)
        zi[: NX * n] = zi[NX : NX * (n + 1)]
        zi[lay.u0 : lay.u0 + n - 1] = zi[lay.u0 + 1 : lay.u0 + n]
        self._shift_idx = zi
        yi = np.arange(lay.m)
        for start, width, count in (
            (lay.r_dyn, NX, n),
            (lay.r_u, 1, n),
            (lay.r_du, 1, n - 1),
            (lay.r_gap, 1, n),
            (lay.r_vhi, 1, n),
            (lay.r_vlo, 1, n),
        ):
            yi[start : start + width * (count - 1)] = yi[start + width : start + width * count]
        self._shift_dual_idx = yi

    def vectors(self, mode: str, inp: QpInputs) -> tuple[Vec, Vec, Vec]:
        """``(q, l, u)`` for this cycle (new arrays)."""
        q, lo, hi = np.empty(self.lay.nz), np.empty(self.lay.m), np.empty(self.lay.m)
        self.vectors_into(mode, inp, q, lo, hi)
        return q, lo, hi

    def vectors_into(self, mode: str, inp: QpInputs, q: Vec, lo: Vec, hi: Vec) -> None:
        """Write this cycle's ``q``, ``l``, ``u`` into the given arrays (no allocation of
        vectors of the QP's size: this runs every cycle)."""
        cfg, lay, n = self.cfg, self.lay, self.lay.N
        np.copyto(q, self._q0[mode])
        vl = np.asarray(inp.v_lead, dtype=float)
        if mode == "follow":
            rel = self.rel_row
            if rel is None:  # T = 0: the relative speed
                q[self._ks_v] -= (2.0 * cfg.q_rel_speed) * vl[1:n]
            else:  # v + T a: the speed's and the current's parts
                q[self._ks_v] -= (2.0 * cfg.q_rel_speed * rel[I_V]) * vl[1:n]
                q[self._ks_v - I_V] -= (2.0 * cfg.q_rel_speed * rel[I_CUR]) * vl[1:n]
            v_end = float(vl[n - 1])
        else:
            q[self._ks_v] -= 2.0 * cfg.q_cruise * inp.v_ref
            v_end = inp.v_ref
        q[lay.u0] -= 2.0 * cfg.r_du * inp.u_prev
        q[self._term_idx] += v_end * self._term_slope[mode]

        np.copyto(lo, self._lo0)
        np.copyto(hi, self._hi0)
        lo[:NX] = inp.x0
        hi[:NX] = inp.x0
        dyn = lo[lay.r_dyn : lay.r_u]
        np.multiply(vl[:, None], self._neg_bl, out=dyn.reshape(n, NX))
        hi[lay.r_dyn : lay.r_u] = dyn
        lo[lay.r_u : lay.r_du] = inp.u_lo
        hi[lay.r_u : lay.r_du] = inp.u_hi
        lo[lay.r_u], hi[lay.r_u] = self.first_move_bounds(inp)
        lo[lay.r_gap : lay.r_vhi] = cfg.d_min if inp.lead else -INF
        hi[lay.r_vhi : lay.r_vlo] = inp.v_cap

    def first_move_bounds(self, inp: QpInputs) -> tuple[float, float]:
        """Bounds of ``u_0`` (V): the voltage bounds and the rate limit from ``u_prev``;
        when ``u_prev`` lies outside the new bounds, the nearest bound."""
        du = self.cfg.du_max * self.cfg.period
        u_prev, u_lo, u_hi = inp.u_prev, inp.u_lo, inp.u_hi
        lo0, hi0 = u_prev - du, u_prev + du  # max(lo0, u_lo), min(hi0, u_hi) written out
        lo0 = u_lo if u_lo > lo0 else lo0
        hi0 = u_hi if u_hi < hi0 else hi0
        if lo0 > hi0:
            lo0 = hi0 = min(max(inp.u_prev, inp.u_lo), inp.u_hi)
        return lo0, hi0

    def first_move(self, z: Vec) -> float:
        """``u_0`` (V) from a solution vector."""
        return float(z[self.lay.u0])

    def shift(self, z: Vec, out: Vec | None = None) -> Vec:
        """A solution shifted one step ahead: the primal warm start (into ``out`` if given).

        The inputs repeat their last step, the slacks stay; the new last state is extrapolated
        with the model (``x_N + Ad (x_N - x_{N-1})`` keeps the lead-speed term of the last
        step), so the guess satisfies the dynamics rows.
        """
        n = self.lay.N
        out = np.take(z, self._shift_idx, out=out)
        x_n = z[NX * n : NX * (n + 1)]
        out[NX * n : NX * (n + 1)] += self.pred.Ad @ (x_n - z[NX * (n - 1) : NX * n])
        return out

    def shift_dual(self, y: Vec, out: Vec | None = None) -> Vec:
        """Constraint multipliers shifted one step ahead, block by block (the dual warm
        start); the last step of each block repeats."""
        return np.take(y, self._shift_dual_idx, out=out)

    def speeds(self, z: Vec) -> Vec:
        """The predicted speeds ``v_0 .. v_N`` (m/s) of a solution: a view, not a copy."""
        return z[I_V : NX * (self.lay.N + 1) : NX]

    def plan(self, z: Vec) -> tuple[Vec, Vec, Vec]:
        """``(u (N,), v (N+1,), d (N+1,))`` of a solution."""
        lay, n = self.lay, self.lay.N
        xs = z[: NX * (n + 1)].reshape(n + 1, NX)
        return z[lay.u0 : lay.u0 + n].copy(), xs[:, I_V].copy(), xs[:, I_D].copy()
