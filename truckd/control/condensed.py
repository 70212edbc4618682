"""The MPC's QP condensed: the states eliminated through the prediction model (pure numerics).

The sparse QP of :mod:`truckd.control.qp` (decision vector ``z = [x_0..x_N, u, sg, sv]``,
``1/2 z'Pz + q'z`` subject to ``l <= A z <= u``) has the dynamics and the initial state as
equality rows.  Every ``z`` that satisfies them is

    z = M w + C0 x_0 + Cl v_lead          (w = [u_0..u_{N-1}, sg, sv])

so the same optimisation over ``w`` alone is

    min 1/2 w'(M'PM)w + (M'q + M'P c)'w    s.t.  l - A c <= (A M) w <= u - A c

with ``c = C0 x_0 + Cl v_lead`` and only the inequality rows of A kept.  Its solution
mapped back (``z = M w + c``) is the sparse QP's solution: the same QP in fewer variables
(42 instead of 165 at N = 40, 201 rows instead of 324), so everything downstream (the
plan, the first move, the check against CLARABEL) sees the sparse layout.  The matrices
``M'PM``, ``AM`` and the products with ``C0``/``Cl`` are built once per mode; each cycle
costs a few small dense matrix-vector products.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from truckd.control.qp import NX, QpBuilder, QpInputs, Vec


class CondensedQp:
    """Per-mode condensed matrices of a :class:`QpBuilder`'s QP and its per-cycle vectors."""

    def __init__(self, qp: QpBuilder) -> None:
        self.qp = qp
        lay, n, pred = qp.lay, qp.lay.N, qp.pred
        self.nw = n + 2
        # z = M w + C0 x0 + Cl vl, column by column by simulating the prediction model.
        m = np.zeros((lay.nz, self.nw))
        c0 = np.zeros((lay.nz, NX))
        cl = np.zeros((lay.nz, n))
        for j in range(n):  # input u_j: zero until step j+1
            x = pred.bu.copy()
            for k in range(j + 1, n + 1):
                m[lay.x(k) : lay.x(k) + NX, j] = x
                x = pred.Ad @ x
            m[lay.u0 + j, j] = 1.0
            x = pred.bl.copy()
            for k in range(j + 1, n + 1):
                cl[lay.x(k) : lay.x(k) + NX, j] = x
                x = pred.Ad @ x
        m[lay.sg0, n] = 1.0
        m[lay.sv0, n + 1] = 1.0
        x = np.eye(NX)
        for k in range(n + 1):
            c0[lay.x(k) : lay.x(k) + NX, :] = x
            x = pred.Ad @ x
        self.M, self.C0, self.Cl = m, c0, cl
        # Inequality rows only (the initial state and dynamics rows hold by construction).
        self.rows = np.arange(lay.r_u, lay.m)
        a = qp.A.tocsr()[self.rows].toarray()
        self.A = a @ m
        self.A[np.abs(self.A) < 1e-14 * np.max(np.abs(self.A))] = 0.0
        self.A_sparse = sp.csc_matrix(self.A)
        self._a_c0 = a @ c0
        self._a_cl = a @ cl
        self.P: dict[str, Vec] = {}
        self._mt = m.T.copy()
        self._mtp_c0: dict[str, Vec] = {}
        self._mtp_cl: dict[str, Vec] = {}
        for mode, p in qp.P.items():
            pd = p.toarray()
            pc = m.T @ pd @ m
            self.P[mode] = 0.5 * (pc + pc.T)
            self._mtp_c0[mode] = m.T @ pd @ c0
            self._mtp_cl[mode] = m.T @ pd @ cl
        self.m = len(self.rows)
        self._q = np.empty(lay.nz)
        self._lo = np.empty(lay.m)
        self._hi = np.empty(lay.m)

    def p_triu(self, mode: str) -> sp.csc_matrix:
        """The upper triangle of the condensed cost matrix (OSQP's form)."""
        return sp.triu(sp.csc_matrix(self.P[mode]), format="csc")

    def vectors_into(self, mode: str, inp: QpInputs, q: Vec, lo: Vec, hi: Vec) -> None:
        """This cycle's condensed ``q``, ``l``, ``u`` written into the given arrays."""
        qs, ls, hs = self._q, self._lo, self._hi
        self.qp.vectors_into(mode, inp, qs, ls, hs)
        x0 = inp.x0
        vl = inp.v_lead
        np.dot(self._mt, qs, out=q)
        q += self._mtp_c0[mode] @ x0
        q += self._mtp_cl[mode] @ vl
        ac = self._a_c0 @ x0
        ac += self._a_cl @ vl
        r0 = self.rows[0]
        np.subtract(ls[r0:], ac, out=lo)
        np.subtract(hs[r0:], ac, out=hi)

    def expand(self, w: Vec, inp: QpInputs) -> Vec:
        """The sparse QP's decision vector ``z = M w + C0 x0 + Cl v_lead``."""
        z: Vec = self.M @ w + self.C0 @ inp.x0 + self.Cl @ inp.v_lead
        return z
