"""Linear part of the motor/drivetrain model: state space and exact discretisation.

States ``x = [i, omega_m]`` (A, rad/s), input the armature voltage (V), friction and
load torques enter as a torque disturbance (N m) at the motor shaft, output the
vehicle speed (m/s):

    L_m di/dt      = V - R_m i - K_v omega_m
    J_S domega_m/dt = K_T i - b omega_m - T_dist
    v              = r_w omega_m / (n_g n_fd)

The electrical time constant ``L_m/R_m`` is well under a millisecond, so explicit
Euler at control rates is wrong; :func:`zoh` gives the exact zero-order-hold
discretisation, :func:`expm2` the closed-form 2x2 matrix exponential used on the
simulator's hot path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.model.params import VehicleParams

Mat2 = tuple[float, float, float, float]
"""A 2x2 matrix as a flat row-major tuple (a00, a01, a10, a11)."""


@dataclass(frozen=True)
class StateSpace:
    """Continuous-time model ``x' = A x + B V + E T_dist``, ``v = C x``."""

    A: NDArray[np.float64]
    B: NDArray[np.float64]
    E: NDArray[np.float64]
    C: NDArray[np.float64]


def system_matrix(p: VehicleParams, viscous: float = 0.0, extra_resistance: float = 0.0) -> Mat2:
    """``A`` as a flat tuple; ``viscous`` in N m s/rad, ``extra_resistance`` in ohm."""
    return (
        -(p.R_m + extra_resistance) / p.L_m,
        -p.K_v / p.L_m,
        p.K_T / p.J_S,
        -viscous / p.J_S,
    )


def state_space(p: VehicleParams, viscous: float = 0.0) -> StateSpace:
    """The seed's state-space matrices (plus an optional viscous term b, N m s/rad)."""
    a = system_matrix(p, viscous)
    return StateSpace(
        A=np.array([[a[0], a[1]], [a[2], a[3]]]),
        B=np.array([[1.0 / p.L_m], [0.0]]),
        E=np.array([[0.0], [-1.0 / p.J_S]]),
        C=np.array([[0.0, p.ratio]]),
    )


def expm2(a: Mat2, t: float) -> Mat2:
    """``exp(A t)`` for a 2x2 ``A`` in closed form (real, complex or repeated eigenvalues).

    Written as a combination of ``exp(lambda_k t)`` so that stiff matrices (fast and slow
    eigenvalues far apart) neither overflow nor lose precision.
    """
    a00, a01, a10, a11 = a
    s = 0.5 * (a00 + a11)
    n00, n11 = a00 - s, a11 - s
    q = n00 * n00 + a01 * a10  # N^2 = q I for the traceless part N
    if q * t * t > 1e-12:
        r = math.sqrt(q)
        e1 = math.exp((s + r) * t)
        e2 = math.exp((s - r) * t)
        c = 0.5 * (e1 + e2)
        sh = 0.5 * (e1 - e2) / r
    elif q * t * t < -1e-12:
        w = math.sqrt(-q)
        es = math.exp(s * t)
        c = es * math.cos(w * t)
        sh = es * math.sin(w * t) / w
    else:
        es = math.exp(s * t)
        qt2 = q * t * t
        c = es * (1.0 + qt2 / 2.0)
        sh = es * t * (1.0 + qt2 / 6.0)
    return (c + sh * n00, sh * a01, sh * a10, c + sh * n11)


def solve2(a: Mat2, b0: float, b1: float) -> tuple[float, float]:
    """``A^{-1} [b0, b1]`` for an invertible 2x2 ``A``."""
    a00, a01, a10, a11 = a
    det = a00 * a11 - a01 * a10
    return ((a11 * b0 - a01 * b1) / det, (a00 * b1 - a10 * b0) / det)


def expm(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Matrix exponential by scaling and squaring with a Taylor series (small matrices).

    Accurate to about machine precision for the well-scaled matrices of this model
    (the daemon uses it instead of importing scipy).
    """
    norm = float(np.max(np.sum(np.abs(m), axis=1))) if m.size else 0.0
    k = max(0, math.ceil(math.log2(norm / 0.25))) if norm > 0.25 else 0
    ms = m / (2.0**k)
    result = np.eye(m.shape[0])
    term = np.eye(m.shape[0])
    for n in range(1, 20):
        term = term @ ms / n
        result = result + term
    for _ in range(k):
        result = result @ result
    return result


def zoh(
    a: NDArray[np.float64], b: NDArray[np.float64], h: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact zero-order-hold discretisation: ``x[k+1] = Ad x[k] + Bd u[k]`` over step h (s)."""
    n, m = a.shape[0], b.shape[1]
    aug = np.zeros((n + m, n + m))
    aug[:n, :n] = a * h
    aug[:n, n:] = b * h
    e = expm(aug)
    return e[:n, :n], e[:n, n:]


def discretize(
    p: VehicleParams, h: float, viscous: float = 0.0
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Exact ZOH of the seed model over h (s): ``(Ad, Bd_voltage, Ed_torque)``."""
    ss = state_space(p, viscous)
    ad, bd = zoh(ss.A, np.hstack([ss.B, ss.E]), h)
    return ad, bd[:, :1], bd[:, 1:]
