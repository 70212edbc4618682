"""Discrete algebraic Riccati equation in numpy (the daemon does not import scipy.linalg).

    X = A'XA - A'XB (R + B'XB)^{-1} B'XA + Q

solved by the structure-preserving doubling algorithm (Chu, Fan, Lin 2005): quadratic
convergence from ``X_0 = Q`` for a stabilisable ``(A, B)`` and a detectable ``(A, Q)``, a
handful of small dense solves for the MPC's 3- and 4-state models.  Pure numerics, no units
of its own (those of the matrices given).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Mat = NDArray[np.float64]


def solve_dare(a: Mat, b: Mat, q: Mat, r: Mat, *, tol: float = 1e-13, max_iter: int = 100) -> Mat:
    """The stabilising solution X (symmetric) of the DARE.

    Raises ValueError when the doubling does not converge within ``max_iter`` steps (the
    pair is not stabilisable/detectable) or produces non-finite numbers.
    """
    n = a.shape[0]
    eye = np.eye(n)
    ak = np.array(a, dtype=float)
    gk = b @ np.linalg.solve(r, b.T)
    hk = np.array(q, dtype=float)
    for _ in range(max_iter):
        w = eye + gk @ hk
        with np.errstate(over="ignore", invalid="ignore"):  # diverging: checked below
            w_a = np.linalg.solve(w, ak)  # W^{-1} A_k
            w_g = np.linalg.solve(w, gk)  # W^{-1} G_k
            h_next = hk + ak.T @ hk @ w_a
            gk = gk + ak @ w_g @ ak.T
            ak = ak @ w_a
        if not (np.all(np.isfinite(h_next)) and np.all(np.isfinite(gk))):
            raise ValueError("DARE: the doubling produced non-finite values")
        done = np.max(np.abs(h_next - hk)) <= tol * max(1.0, float(np.max(np.abs(h_next))))
        hk = h_next
        if done:
            x: Mat = 0.5 * (hk + hk.T)
            return x
    raise ValueError(f"DARE: no convergence in {max_iter} doubling steps")
