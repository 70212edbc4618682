"""Free run of a force-input model (a rig driven by a known force): the first-order
engine of :mod:`truckd.ident.freerun` with the force as its input.  Pure numerics, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.ident.freerun import Kinetics, run, timeline

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ForceModel:
    """Rigid body with friction under a force input (SI, load side).

    ``M dv/dt = F - F_v v - F_c sign(v) - offset - c_drag v|v|``; held at rest while
    ``|F - offset| <= F_s`` (``F_s`` defaults to ``F_c``).
    """

    M: float
    F_c: float
    F_v: float = 0.0
    offset: float = 0.0
    F_s: float | None = None
    c_drag: float = 0.0


def simulate_force(m: ForceModel, t: Array, f: Array, v0: float = 0.0) -> tuple[Array, Array]:
    """Free run of a force-input model: per-sample (speed m/s, position m from 0)."""
    n = len(t)
    fs = m.F_c if m.F_s is None else m.F_s
    b = m.F_v / m.M
    kin = Kinetics(
        a=np.asarray(f, float) / m.M,
        b=np.full(n, b),
        a_idle=0.0,
        b_idle=b,
        c=m.F_c / m.M,
        sigma=fs / m.M,
        d=m.offset / m.M,
        drag=m.c_drag / m.M,
    )
    tl = timeline(np.asarray(t, float), 0.0)
    _, raw, pos = run(kin, tl, n, v0)
    return raw, pos
