"""Fallback laws when the MPC has no fresh solution: the shifted plan, then braking.

Pure numerics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray


def braking_law(v: float, gain: float, u_max: float) -> float:
    """Brake to standstill: ``u = -gain v`` (V), clipped to ``[-u_max, 0]``; 0 at rest."""
    if not math.isfinite(v) or v <= 0.0:
        return 0.0
    return max(-u_max, -gain * v)


def held_plan_move(
    plan: Sequence[float] | NDArray[np.float64] | None, age: int, max_age: int
) -> float | None:
    """Move ``age`` steps into the last good plan (V; a list or an array), or None when it
    is too old/short."""
    if plan is None or age > max_age or age >= len(plan):
        return None
    return float(plan[age])


def limit_command(u: float, u_prev: float, u_max: float, du: float) -> float:
    """The command made safe: finite, within ``+-u_max`` and ``du`` of the previous one.

    A non-finite request becomes 0 V (moved towards at the rate limit).
    """
    if not math.isfinite(u):
        u = 0.0
    if not math.isfinite(u_prev):
        u_prev = 0.0
    # min(max(u, lo), hi) written out, twice (the builtins parse their arguments as a
    # keyword call: several times the comparisons' cost, every cycle)
    lo, hi = u_prev - du, u_prev + du
    u = lo if lo > u else u
    u = hi if hi < u else u
    u = -u_max if -u_max > u else u
    return u_max if u_max < u else u
