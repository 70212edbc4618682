"""The armature's electrical pole in the first-order model of the fast simulator.

The two-state motor (current and speed) has a slow and a fast eigenvalue; the fitting
loop's first-order model runs at the slow one and keeps the fast one as a pure lag of the
input (:mod:`truckd.ident.fastsim`).  Pure numerics, no I/O.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from truckd.model.params import VehicleParams

Array = NDArray[np.float64]


def electrical_correction(
    p: VehicleParams, viscous: float = 0.0, resistance: Array | float | None = None
) -> tuple[Array | float, Array | float]:
    """What the neglected electrical pole does to the first-order model.

    Returns ``(kappa, lag)`` for the armature circuit resistance ``resistance`` (ohm,
    default ``R_m``; an array gives arrays): the exact slow eigenvalue of the two-state
    model over the quasi-static one (time runs ``kappa`` times faster, steady states
    unchanged) and the fast pole's time constant (s), kept as a pure lag of the input.
    """
    if resistance is None:
        # in floats: the same operations in the same order (IEEE doubles either way),
        # without numpy's overhead on scalars
        try:
            return _correction(float(p.R_m), p, viscous, math.sqrt, max)
        except ZeroDivisionError:
            pass  # numpy's inf and nan, as for an array
    r = np.asarray(p.R_m if resistance is None else resistance, float)
    return _correction(r, p, viscous, np.sqrt, np.maximum)


def _correction(
    r: Any, p: VehicleParams, viscous: float, sqrt: Callable[[Any], Any], most: Callable[..., Any]
) -> tuple[Any, Any]:
    """:func:`electrical_correction` at the resistance ``r`` (a float or an array, with
    the ``sqrt`` and ``most`` (max) of its kind)."""
    tr = -(r / p.L_m + viscous / p.J_S)
    det = (r * viscous + p.K_v * p.K_T) / (p.L_m * p.J_S)
    disc = sqrt(most(tr * tr / 4.0 - det, 0.0))
    lam_s, lam_f = tr / 2.0 + disc, tr / 2.0 - disc
    beta = (p.K_T * p.K_v / r + viscous) / p.J_S
    return -lam_s / beta, -1.0 / lam_f
