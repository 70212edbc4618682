"""The MPC's QP condensed and move-blocked: the states eliminated, the inputs held over
blocks of steps (pure numerics).

The sparse QP of :mod:`truckd.control.qp` (decision vector ``z = [x_0..x_N, u, sg, sv]``,
``1/2 z'Pz + q'z`` subject to ``l <= A z <= u``) has the initial state and the dynamics
as equality rows.  Every ``z`` that satisfies them is

    z = M u_s + C0 x_0 + Cl v_lead          (u_s = [u_0..u_{N-1}, sg, sv])

and with the inputs held constant over blocks of ``L_0, L_1, ..`` steps (move blocking,
``u_s = E w``, ``w = [w_0..w_{B-1}, sg, sv]``) the QP over ``w`` alone is

    min 1/2 w'(E'M'PME)w + (E'M'(q + P c))'w    s.t.  the rows below,  c = C0 x_0 + Cl v_lead

with rows: each block's input within the voltage bounds (the first also within the rate
limit of the previous command), the change between consecutive blocks within the rate
limit (it happens in one step), and the state rows of the sparse QP (``A_s M E w`` between
``l - A_s c`` and ``u - A_s c``): every step's minimum gap, the speed limits at each block's
first and last step (:func:`speed_steps`: the speed is monotone in between), the slacks.  OSQP
sees them ordered minimum gap, no reverse, block inputs, speed limit, block changes,
slacks (:attr:`CondensedQp.state_rows`, ``block_rows``, ``change_rows`` say where each
went), so that the bounds that change from cycle to cycle form one stretch (see
``__init__``).  The
solution mapped back (``z = M E w + c``) has the sparse layout, so the plan, the first move
and the checks downstream are unchanged.

With one step per block this is the sparse QP itself, condensed (measured slower: its
dense rows cost more per OSQP iteration than the sparse KKT system).  With 8 blocks at
N = 40 (1, 1, 2, 4, 8, 8, 8, 8 steps) it has 10 variables and 85 rows (137 with every
step's speed rows) instead of 165 and 324: see docs/controller.md for the time and the
closed-loop effect.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from truckd.control.qp import I_CUR, I_V, INF, INPUT_LIMIT, NX, QpBuilder, QpInputs, Vec, inputs_ok

Mat = NDArray[np.float64]

N_SCALARS = 8
"""Scalar inputs between x0 and v_lead: u_prev, v_ref, u_lo, u_hi, v_cap, 1, and the first
block's bounds."""


def block_lengths(horizon: int, blocks: int, max_len: int | None = None) -> tuple[int, ...]:
    """Steps per block: 1, 1, then doubling while the rest of the horizon still spreads
    evenly over the remaining blocks, the rest evenly (the last takes what is left).

    ``blocks >= horizon`` gives one step per block.  E.g. (40, 8): 1, 1, 2, 4, 8, 8, 8, 8.
    ``max_len``: no block longer than this many steps; a longer one is split evenly (more
    blocks than ``blocks``), e.g. (40, 8, 5): 1, 1, 2, 4, 4, 4, 4, 4, 4, 4, 4, 4
    (see :func:`max_block_steps`).
    """
    if horizon < 1 or blocks < 1:
        raise ValueError(f"horizon {horizon} and blocks {blocks} must be positive")
    if max_len is not None and max_len < 1:
        raise ValueError(f"max_len {max_len} must be positive")
    if blocks >= horizon:
        return (1,) * horizon
    out = _doubling_blocks(horizon, blocks)
    if max_len is None or max(out) <= max_len:
        return out
    split: list[int] = []
    for n in out:
        parts = -(-n // max_len)  # ceil
        split += [n // parts + (1 if i < n % parts else 0) for i in range(parts)]
    return tuple(split)


def max_block_steps(tau_m: float, period: float, fraction: float) -> int | None:
    """The longest input block (steps of ``period``, s) for a truck whose mechanical time
    constant is ``tau_m`` (s, ``J_S R_m / (K_T K_v)``): ``fraction`` of it, at least one
    step; None (no limit) when ``fraction`` is 0 (``control.block_tau_fraction``).

    A block holds the voltage; the back-EMF turns a held voltage into an acceleration that
    decays with ``tau_m``.  With blocks long against ``tau_m`` the blocked plan cannot hold
    a deceleration (a braking lead) that the truck can, so a truck with a short ``tau_m``
    (light, or a strong motor) tracks looser than one with a long one under the same
    weights: in a platoon of different trucks its spacing error is larger than its
    predecessor's (docs/platoon.md, "Mixed trucks").  At 0.5 the shipped truck (0.167 s
    at 100 Hz: 8 steps) keeps its 1, 1, 2, 4, 8, 8, 8, 8."""
    if fraction <= 0.0:
        return None
    return max(1, int(fraction * tau_m / period + 1e-9))


SPEED_RIPPLE_MAX = 0.005
"""m/s: how far the speed may stray beyond its values at a block's first and last step for
the QP to constrain it there only (:func:`speed_steps`): a quarter of the at-rest speed
(``moving_speed``, 0.02 m/s), a tenth of one encoder tick per period at 100 Hz."""


def speed_steps(ad: Mat, blocks: tuple[int, ...], u_max: float, v_max: float) -> tuple[int, ...]:
    """Steps ``k`` whose predicted speed ``v_{k+1}`` the QP constrains (speed limit and no
    reverse), for the discrete model ``ad`` (states ``[e, v, d]``, e and voltages in V,
    speeds in m/s), move blocks ``blocks``, voltage limit ``u_max`` and speed limit ``v_max``.

    Under a block's constant input the current and the speed (the gap does not feed back)
    relax along two modes towards the block's equilibrium.  With two real, positive modes,
    from the block's first step on the speed is the slow, mechanical mode's exponential,
    monotone to the block's end, plus what is left of the fast, electrical one, at most
    ``2 |b| lambda_f`` (``lambda_f`` the fast mode over one period, ``b`` its speed part for
    any start within twice the limits).  Otherwise (complex or negative modes: the motor
    rings) nothing is monotone, but after one period the speed lies within ``B = sum_i
    |b_i| |lambda_i|`` of the equilibrium, so within ``2 B`` of the block's last speed.
    When that remainder is under :data:`SPEED_RIPPLE_MAX` the speed's extremes over a
    block lie at its first and last step (to within it), and each block keeps those two
    rows: 14 of 40 steps with 8 blocks at N = 40 (the configured truck: 1e-10 m/s at
    100 Hz, 1.7 mm/s at 500 Hz; a truck with a hundredth of its inertia, whose modes are
    complex but vanish within a period, 2e-3 m/s).  Otherwise (the current's transient or
    the ringing outlasting the period) every step keeps its rows."""
    n = sum(blocks)
    modes, right = np.linalg.eig(ad[:2, :2])
    left = np.linalg.inv(right)
    starts = np.abs(left[:, 0]) * 4.0 * u_max + np.abs(left[:, 1]) * 2.0 * v_max
    remainders = np.abs(right[1, :]) * starts * np.abs(modes)
    if np.all(modes.imag == 0.0) and np.all(modes.real >= 0.0):
        ripple = 2.0 * float(remainders[int(np.argmin(np.abs(modes)))])
    else:
        ripple = 2.0 * float(np.sum(remainders))
    if not ripple <= SPEED_RIPPLE_MAX:
        return tuple(range(n))
    out: list[int] = []
    first = 0
    for length in blocks:
        out += sorted({first, first + length - 1})
        first += length
    return tuple(out)


def _doubling_blocks(horizon: int, blocks: int) -> tuple[int, ...]:
    out: list[int] = []
    rest = horizon
    for i in range(blocks):
        left = blocks - i
        if left == 1:
            out.append(rest)
            break
        want = 1 if i < 2 else 2 * out[-1]
        n = max(1, min(want, rest // left))
        out.append(n)
        rest -= n
    return tuple(out)


class CondensedQp:
    """The move-blocked, condensed form of a :class:`QpBuilder`'s QP (see module doc)."""

    def __init__(self, qp: QpBuilder, blocks: tuple[int, ...]) -> None:
        n = qp.lay.N
        if sum(blocks) != n or min(blocks) < 1:
            raise ValueError(f"blocks {blocks} must be positive and sum to the horizon {n}")
        self.qp = qp
        self.blocks = blocks
        nb = len(blocks)
        self.nb = nb
        self.nw = nb + 2
        self.ME, self.C0, self.Cl = self._prediction(qp, blocks)
        self.speed_steps = speed_steps(qp.pred.Ad, blocks, qp.cfg.u_max, qp.cfg.v_max)
        """Steps ``k`` whose speed ``v_{k+1}`` keeps its rows (speed limit, no reverse)."""
        perm, r = self._constraint_rows(qp)
        self._cost_terms(qp)
        full = self._fill_matrices(qp, perm, r)
        self._constant_stretches(full)

    def _prediction(self, qp: QpBuilder, blocks: tuple[int, ...]) -> tuple[Mat, Mat, Mat]:
        """``(ME, C0, Cl)``: the predicted sparse vector z = ME w + C0 x0 + Cl v_lead of the
        blocked inputs ``w`` (block inputs, then the two slacks)."""
        lay, n, pred, nb = qp.lay, qp.lay.N, qp.pred, self.nb
        # z = M u_s + C0 x0 + Cl vl, column by column by simulating the prediction model.
        m = np.zeros((lay.nz, n + 2))
        c0 = np.zeros((lay.nz, NX))
        cl = np.zeros((lay.nz, n))
        for j in range(n):  # input u_j (and lead speed over step j): from step j+1 on
            xu, xl = pred.bu.copy(), pred.bl.copy()
            for k in range(j + 1, n + 1):
                m[lay.x(k) : lay.x(k) + NX, j] = xu
                cl[lay.x(k) : lay.x(k) + NX, j] = xl
                xu, xl = pred.Ad @ xu, pred.Ad @ xl
            m[lay.u0 + j, j] = 1.0
        m[lay.sg0, n] = 1.0
        m[lay.sv0, n + 1] = 1.0
        x = np.eye(NX)
        for k in range(n + 1):
            c0[lay.x(k) : lay.x(k) + NX, :] = x
            x = pred.Ad @ x
        e = np.zeros((n + 2, self.nw))
        k = 0
        for b, length in enumerate(blocks):
            e[k : k + length, b] = 1.0
            k += length
        e[n, nb] = e[n + 1, nb + 1] = 1.0
        me = m @ e
        return me, c0, cl

    def _constraint_rows(self, qp: QpBuilder) -> tuple[Vec, int]:
        """The condensed constraint matrix :attr:`A` in OSQP's row order; returns that
        order (``perm``) and the first state row in the order built (``r``)."""
        lay, n, nb, me = qp.lay, qp.lay.N, self.nb, self.ME
        # Rows: block inputs (nb), block changes (nb - 1), the sparse QP's state and slack
        # rows (from its minimum-gap block to the end; speed rows at speed_steps only).
        ks = np.array(self.speed_steps, dtype=np.intp)
        nv = ks.size
        self.state_sel = np.concatenate(
            [np.arange(n), n + ks, 2 * n + ks, 3 * n + np.arange(lay.m - lay.r_slack)]
        )
        """The sparse QP's rows ``r_gap`` .. end kept (offsets from ``r_gap``), in order."""
        a_state = qp.A.tocsr()[lay.r_gap :].toarray()[self.state_sel]
        self.m = 2 * nb - 1 + a_state.shape[0]
        a = np.zeros((self.m, self.nw))
        a[np.arange(nb), np.arange(nb)] = 1.0
        for b in range(1, nb):
            a[nb + b - 1, b] = 1.0
            a[nb + b - 1, b - 1] = -1.0
        a_me = a_state @ me
        a_me[np.abs(a_me) < 1e-15 * np.max(np.abs(a_me))] = 0.0
        a[2 * nb - 1 :] = a_me
        # OSQP's row order: minimum gap (n), no reverse (n), block inputs (nb), speed limit
        # (n), block changes (nb - 1), slacks, so that the bounds that change from cycle to
        # cycle are one stretch of fill's buffer (see there).  In the order built above:
        r = 2 * nb - 1
        gap, vhi, vlo, slack = r, r + n, r + n + nv, r + n + 2 * nv
        perm = np.concatenate(
            [
                np.arange(gap, gap + n),
                np.arange(vlo, vlo + nv),
                np.arange(0, nb),
                np.arange(vhi, vhi + nv),
                np.arange(nb, r),
                np.arange(slack, self.m),
            ]
        )
        if not np.array_equal(np.sort(perm), np.arange(self.m)):
            raise AssertionError(f"row order {perm} is not a permutation")
        row_of = np.argsort(perm)  # row_of[i]: where row i of the order above went
        self.block_rows = row_of[:nb]
        """Rows of the block inputs' bounds (the first: the rate-limited first move)."""
        self.change_rows = row_of[nb:r]
        """Rows of the changes between consecutive blocks (within the rate limit)."""
        self.state_rows = row_of[r:]
        """Rows of the sparse QP's rows :attr:`state_sel`, in that order."""
        self.A = sp.csc_matrix(a[perm])
        self._a_c0 = a_state @ self.C0
        self._a_cl = a_state @ self.Cl
        self.P: dict[str, sp.csc_matrix] = {}
        return perm, r

    def _cost_terms(self, qp: QpBuilder) -> None:
        """The condensed Hessians :attr:`P` and the affine pieces of the linear term."""
        lay, n, me, c0, cl = qp.lay, qp.lay.N, self.ME, self.C0, self.Cl
        # q_c = E'M'(q_s + P c) with the sparse q_s affine in the inputs (qp.vectors_into):
        # q_s = q0 + (follow) -2 q_rel v_lead[1:N] | (cruise) -2 q_cruise v_ref, at the
        # speeds of steps 1..N-1; - 2 r_du u_prev at u_0; v_end times the terminal slope
        # (v_end = v_lead[N-1] following, v_ref cruising).  So q_c = g0 + Hx x0 + Hl v_lead
        # + g_u u_prev + g_ref v_ref, all built here.
        met = me.T
        cfg = qp.cfg
        self._g0: dict[str, Vec] = {}
        self._hx: dict[str, Vec] = {}
        self._hl: dict[str, Vec] = {}
        self._g_ref: dict[str, Vec] = {}
        self._g_u = -2.0 * cfg.r_du * met[:, lay.u0]
        speeds = met[:, qp._ks_v]  # columns of the speeds of steps 1..N-1
        for mode, p in qp.P.items():
            pd = p.toarray()
            pc = met @ pd @ me
            self.P[mode] = sp.csc_matrix(0.5 * (pc + pc.T))
            term = met[:, qp._term_idx] @ qp._term_slope[mode]
            self._g0[mode] = met @ qp._q0[mode]
            self._hx[mode] = met @ pd @ c0
            hl = met @ pd @ cl
            if mode == "follow":
                # the follow term's linear part: -2 q_rel v_lead times its row on the
                # state (v + T a: the speed and, for T > 0, the current)
                rel, row = speeds, qp.rel_row
                if row is not None:
                    rel = speeds * row[I_V] + met[:, qp._ks_v - I_V] * row[I_CUR]
                hl[:, 1:n] += -2.0 * cfg.q_rel_speed * rel
                hl[:, n - 1] += term
                self._g_ref[mode] = np.zeros(self.nw)
            else:
                self._g_ref[mode] = -2.0 * cfg.q_cruise * speeds.sum(axis=1) + term
            self._hl[mode] = hl

    def _fill_matrices(self, qp: QpBuilder, perm: Vec, r: int) -> dict[tuple[str, bool], Mat]:
        """One matrix per (mode, lead) that maps the cycle's inputs to ``[u; q; l]``."""
        lay, n, nb, me, c0, cl, cfg = qp.lay, qp.lay.N, self.nb, self.ME, self.C0, self.Cl, qp.cfg
        # Bounds of the state and slack rows without the lead/limit-dependent parts.
        _, lo_t, hi_t = qp.vectors(
            "cruise",
            QpInputs(np.zeros(NX), 0.0, np.zeros(n), False, 0.0, 0.0, -1.0, 1.0),
        )
        self._lo_state = lo_t[lay.r_gap :][self.state_sel]
        self._hi_state = hi_t[lay.r_gap :][self.state_sel]
        self._du = cfg.du_max * cfg.period
        # Everything per cycle in few matrix-vector products, bounds included:
        # F [x0; u_prev; v_ref; u_lo; u_hi; v_cap; 1; lo0; hi0; v_lead] = [u; q; l], with
        # the first block's bounds (the rate-limited first move, not linear in the inputs)
        # passed in as lo0, hi0: each numpy call and each line of matrix costs several
        # times more in the loop than back to back (cold caches after the period's sleep),
        # so few calls and small matrices.  One F per mode and lead/no lead (the gap rows'
        # lower bound is d_min or none).
        nw, m = self.nw, self.m
        c_u, c_ref, c_lo, c_hi, c_cap, c_1, c_lo0, c_hi0 = range(NX, NX + N_SCALARS)
        c_vl = slice(NX + N_SCALARS, NX + N_SCALARS + n)
        # One buffer [w; x0; scalars; v_lead]: fill() writes the inputs behind w, plan()
        # puts the solution in front.
        self._ws = np.zeros(nw + NX + n + N_SCALARS)
        self._s = self._ws[nw:]
        self._s[c_1] = 1.0
        self._filled: list[float] | Vec = []
        # plan: what the cycle uses of the solution, the inputs (V: each step its block's,
        # a gather from w) and the speeds (one product of 41 rows with [w; x0]; the speed
        # of the lead reaches only the gap states).  The whole sparse vector (expand) is
        # three times the matrix and is made only on request.
        v_rows = np.arange(lay.x(0) + I_V, lay.x(n) + NX, NX)
        if np.any(cl[v_rows] != 0.0):
            raise AssertionError("the lead's speed must not reach the predicted speeds")
        self._plan_v = np.ascontiguousarray(np.hstack([me, c0])[v_rows])
        self._ws_a = self._ws[: nw + NX]
        self._u_block = np.repeat(np.arange(nb), self.blocks)
        """The block of each step: ``u_k = w[_u_block[k]]``."""
        full: dict[tuple[str, bool], Mat] = {}
        for mode in qp.P:
            for lead in (False, True):
                f = np.zeros((nw + 2 * m, NX + n + N_SCALARS))  # rows [q; l; u], A's order
                f[:nw, :NX] = self._hx[mode]
                f[:nw, c_vl] = self._hl[mode]
                f[:nw, c_u] = self._g_u
                f[:nw, c_ref] = self._g_ref[mode] if mode != "follow" else 0.0
                f[:nw, c_1] = self._g0[mode]
                lo_rows, hi_rows = nw + np.arange(m), nw + m + np.arange(m)
                for rows in (lo_rows, hi_rows):
                    f[rows[r:], :NX] = -self._a_c0
                    f[rows[r:], c_vl] = -self._a_cl
                f[lo_rows[0], c_lo0] = 1.0
                f[hi_rows[0], c_hi0] = 1.0
                f[lo_rows[1:nb], c_lo] = 1.0
                f[hi_rows[1:nb], c_hi] = 1.0
                f[lo_rows[nb:r], c_1] = -self._du
                f[hi_rows[nb:r], c_1] = self._du
                f[lo_rows[r:], c_1] = self._lo_state
                f[hi_rows[r:], c_1] = self._hi_state
                if lead:  # the minimum gap replaces the state rows' own lower bound
                    f[lo_rows[r : r + n], c_1] = cfg.d_min
                # speed rows: the cap replaces the state rows' own upper bound
                v_hi = hi_rows[r + n : r + n + len(self.speed_steps)]
                f[v_hi, c_1] = 0.0
                f[v_hi, c_cap] = 1.0
                # A side at +-INF stays there whatever the inputs (within qp.INPUT_LIMIT
                # their terms are below half of INF's spacing): a constant.
                unbounded = np.abs(f[:, c_1]) >= INF
                f[np.ix_(unbounded, np.arange(f.shape[1]) != c_1)] = 0.0
                # The buffer is [u; q; l] with the rows reordered (see below).
                full[(mode, lead)] = f[np.concatenate([nw + m + perm, np.arange(nw), nw + perm])]
        return full

    def _constant_stretches(self, full: dict[tuple[str, bool], Mat]) -> None:
        """The per-cycle products over the stretch of the buffer that moves, the rest of
        the buffer written once."""
        nw, m, n = self.nw, self.m, self.qp.lay.N
        c_1 = NX + 5
        c_vl = slice(NX + N_SCALARS, NX + N_SCALARS + n)
        # Half of the bounds never change: the no-reverse and minimum-gap rows have no upper
        # bound, the speed-limit rows no lower one (+-INF absorbs any physical input, see
        # qp.INPUT_LIMIT), the block changes and the slacks constant ones.  With the rows
        # ordered gap, no-reverse, blocks, speed limit, changes, slacks and the buffer
        # [u; q; l], every bound that changes lies in one stretch of 103 of its 180 rows
        # (N = 40, 8 blocks): the products compute that stretch only, the rest is written
        # once here.
        moving = np.zeros(nw + 2 * m, dtype=bool)
        for f in full.values():
            moving |= np.any(f[:, np.arange(f.shape[1]) != c_1] != 0.0, axis=1)
        idx = np.flatnonzero(moving)
        self._span = slice(int(idx[0]), int(idx[-1]) + 1)
        fixed = np.ones(nw + 2 * m, dtype=bool)
        fixed[self._span] = False
        consts = [f[fixed, c_1] for f in full.values()]
        if any(not np.array_equal(c, consts[0]) for c in consts):
            raise AssertionError("the bounds outside the product must not depend on mode or lead")
        self._buf = np.empty(nw + 2 * m)
        self._buf[fixed] = consts[0]
        # The lead's speed reaches only q and the minimum-gap rows (one stretch of the
        # buffer): the rows around them are products of [x0; scalars] alone (25 instead
        # of 42 kB of matrix per cycle, three products instead of one).
        on_lead = np.zeros(nw + 2 * m, dtype=bool)
        for f in full.values():
            on_lead |= np.any(f[:, c_vl] != 0.0, axis=1)
        lead_idx = np.flatnonzero(on_lead)
        lead_rows = slice(int(lead_idx[0]), int(lead_idx[-1]) + 1)
        pieces = [
            (slice(self._span.start, lead_rows.start), self._s[: NX + N_SCALARS]),
            (lead_rows, self._s),
            (slice(lead_rows.stop, self._span.stop), self._s[: NX + N_SCALARS]),
        ]
        pieces = [(rows, src) for rows, src in pieces if rows.stop > rows.start]
        self._products: dict[tuple[str, bool], list[tuple[Vec, Vec, Vec]]] = {}
        for key, f in full.items():
            self._products[key] = [
                (np.ascontiguousarray(f[rows, : src.size]), src, self._buf[rows])
                for rows, src in pieces
            ]
        # A lead at one speed over the whole horizon (every cycle without a forecast, and
        # with no lead): the lead speed's columns summed into one, and the whole stretch in
        # one product of 12 columns (10 instead of 25 kB of matrix, one call instead of 3).
        n_const = NX + N_SCALARS + 1
        self._s_const = self._s[:n_const]
        """``[x0; scalars; v_lead[0]]``: a view of the inputs :meth:`fill` writes."""
        self._products_const: dict[tuple[str, bool], tuple[Vec, Vec]] = {}
        for key, f in full.items():
            g = f[self._span]
            fc = np.empty((g.shape[0], n_const))
            fc[:, : NX + N_SCALARS] = g[:, : NX + N_SCALARS]
            fc[:, -1] = g[:, c_vl].sum(axis=1)
            self._products_const[key] = (fc, self._buf[self._span])
        self._span_full = {key: np.ascontiguousarray(f[self._span]) for key, f in full.items()}
        """The stretch's matrix over all the inputs, one per (mode, lead): the compiled cycle's
        (:mod:`truckd.control.ccycle`) one product."""
        self.hi_view, self.q_view, self.lo_view = (
            self._buf[:m],
            self._buf[m : m + nw],
            self._buf[m + nw :],
        )
        """``u``, ``q``, ``l`` as :meth:`fill` leaves them (views of one buffer)."""

    @property
    def span(self) -> slice:
        """The stretch of :attr:`buffer` the per-cycle product writes (the rest is constant)."""
        return self._span

    @property
    def buffer(self) -> Vec:
        """``[u; q; l]`` of the QP in OSQP's row order (:attr:`hi_view`, :attr:`q_view`,
        :attr:`lo_view` are views of it)."""
        return self._buf

    def span_matrix(self, key: tuple[str, bool]) -> Vec:
        """The stretch :attr:`span` of the buffer as a matrix times ``[x0; scalars;
        v_lead]`` (``key``: mode, lead)."""
        return self._span_full[key]

    def const_matrix(self, key: tuple[str, bool]) -> Vec:
        """:meth:`span_matrix` for a lead at one speed: times ``[x0; scalars; v_lead[0]]``."""
        return self._products_const[key][0]

    def plan_matrix(self) -> Vec:
        """The predicted speeds ``v_0 .. v_N`` as a matrix times ``[w; x0]``."""
        return self._plan_v

    def step_blocks(self) -> NDArray[np.intp]:
        """The block of each step: ``u_k = w[step_blocks()[k]]``."""
        return self._u_block

    def p_triu(self, mode: str) -> sp.csc_matrix:
        """The upper triangle of the condensed cost matrix (OSQP's form)."""
        return sp.triu(self.P[mode], format="csc")

    def fill(self, mode: str, inp: QpInputs) -> bool:
        """This cycle's condensed ``q``, ``l``, ``u`` into :attr:`q_view`, :attr:`lo_view`,
        :attr:`hi_view` (equal to condensing :meth:`QpBuilder.vectors_into`'s).

        Returns False, and leaves the vectors as they were, when the inputs (x0, v_lead,
        u_prev, v_ref, u_lo, u_hi, v_cap) fail :func:`~truckd.control.qp.inputs_ok`."""
        values = self.gather(inp)
        if values is None:
            return False
        self._s[:] = values
        v_lead = values[NX + N_SCALARS :]
        if v_lead.count(v_lead[0]) == len(v_lead):  # one speed: one short product
            f_c, dst = self._products_const[(mode, inp.lead)]
            np.dot(f_c, self._s_const, out=dst)
            return True
        for f, src, dst in self._products[(mode, inp.lead)]:
            np.dot(f, src, out=dst)
        return True

    @property
    def filled(self) -> list[float]:
        """The inputs of the last :meth:`fill` as Python floats: ``[x0; u_prev, v_ref,
        u_lo, u_hi, v_cap, 1, lo0, hi0; v_lead]`` (kept as given, a list or a copy of the
        compiled cycle's array, made Python floats when read)."""
        f = self._filled
        if not isinstance(f, list):
            f = self._filled = f.tolist()
        return f

    @filled.setter
    def filled(self, values: list[float] | Vec) -> None:
        self._filled = values

    n_fixed_inputs = NX + N_SCALARS
    """Inputs before ``v_lead`` in :meth:`gather`'s list."""

    def gather(self, inp: QpInputs) -> list[float] | None:
        """The inputs as Python floats, ``[x0; u_prev, v_ref, u_lo, u_hi, v_cap, 1, lo0,
        hi0; v_lead]`` (kept as :attr:`filled`), or None when they fail
        :func:`~truckd.control.qp.inputs_ok`."""
        # the first block: the sparse QP's first-move bounds (rate-limited)
        lo0, hi0 = self.qp.first_move_bounds(inp)
        # Gathered as Python floats (the controller passes lists: no numpy call until the
        # one copy into the work vector) and checked in Python, before the product below
        # could turn a NaN or a huge value into numpy warnings.  Each numpy call is a code
        # path that is cold after the period's sleep (10-20 us of the cycle, measured).
        scalars = (inp.u_prev, inp.v_ref, inp.u_lo, inp.u_hi, inp.v_cap, 1.0, lo0, hi0)
        head = [*map(float, inp.x0), *map(float, scalars)]
        vl = inp.v_lead
        n = len(vl)
        if n + len(head) != self._s.size:
            raise ValueError(f"x0 and v_lead: {n + len(head)} inputs, expected {self._s.size}")
        if type(vl) is list and type(vl[0]) is float and vl.count(vl[0]) == n:
            # A lead at one speed (the controller's list of one float, repeated): the same
            # list and the same check as below without a call per element (inputs_ok's
            # sum over the same magnitudes in the same order).
            x = vl[0]
            if not sum([*map(abs, head), *[abs(x)] * n]) < INPUT_LIMIT:
                return None
            values = [*head, *[x] * n]
        else:
            values = [*head, *map(float, vl)]
            if not inputs_ok(values):
                return None
        self.filled = values  # kept: the solution can be expanded later
        return values

    def vectors_into(self, mode: str, inp: QpInputs, q: Vec, lo: Vec, hi: Vec) -> None:
        """:meth:`fill`, copied into the given arrays."""
        self.fill(mode, inp)
        q[:] = self.q_view
        lo[:] = self.lo_view
        hi[:] = self.hi_view

    def plan(self, w: Vec) -> tuple[Vec, Vec]:
        """``(u (N,), v (N+1,))`` of a condensed solution ``w`` for the inputs of the last
        :meth:`fill` (new arrays): the planned voltages (V) and the predicted speeds
        ``v_0 .. v_N`` (m/s), as in the sparse layout's inputs and speed states."""
        self._ws[: self.nw] = w
        v: Vec = np.dot(self._plan_v, self._ws_a)
        u: Vec = w.take(self._u_block)
        return u, v

    def expand_filled(self, w: Vec, filled: list[float] | Vec) -> Vec:
        """:meth:`expand` for inputs kept from a :meth:`fill` (its :attr:`filled`)."""
        return self.expand(w, np.array(filled[:NX]), np.array(filled[NX + N_SCALARS :]))

    def expand(self, w: Vec, x0: Vec, v_lead: Vec) -> Vec:
        """The sparse QP's decision vector ``z = M E w + C0 x0 + Cl v_lead`` (a new
        array): every state, input and slack (tests, tools; the cycle needs only
        :meth:`plan`)."""
        z: Vec = self.ME @ w + self.C0 @ x0 + self.Cl @ v_lead
        return z
