"""The state over an input delay: a Smith-predictor-like forward prediction through the
commands already sent but not yet acting (:meth:`truckd.control.controller.Controller`
plans from its end).  Pure: no I/O, no clock."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from truckd.control.qp import Prediction, Vec


def predict_pipeline(
    pred: Prediction,
    x0: Sequence[float],
    pending: Sequence[float],
    v_lead: Sequence[float],
    ff0: float,
    x_pos: float,
    dt: float,
    feedforward: Callable[[float, float], float],
    at_rest: Callable[[float, float], float] | None,
    moving: float,
) -> tuple[Vec, list[float], float, float]:
    """``(x, speeds, ff, x_pos)`` after the ``pending`` commands (V, one per step of ``dt``
    s) from the state ``x0`` (the QP's: ``R_m i`` relative to the feedforward, speed m/s,
    gap m), with the lead at ``v_lead[k]`` (m/s) in step k.

    Each step's friction-free input is the command less the feedforward (V) at that
    step's speed and position (``feedforward(v, x)``; the first step's is ``ff0``); at
    rest (``|v| <= moving``) ``at_rest(u, x)`` gives it instead (stiction and the load take
    up to the breakaway voltage; None: no feedforward).  A truck the prediction brings to
    rest stays there (friction does not drive it backwards).  ``speeds`` starts with
    ``x0``'s speed and has one more per step; ``ff`` is the last step's feedforward and
    ``x_pos`` (m) the position at the end."""
    # In floats, not numpy: three states a step, up to tens of steps a cycle (a 3-vector
    # numpy expression costs microseconds; these are the same products and sums).
    ad = pred.Ad.tolist()
    bu = pred.bu.tolist()
    bl = pred.bl.tolist()
    e, v, d = (float(c) for c in x0)
    speeds = [v]
    ff_k = ff0
    for k, u in enumerate(pending):
        v_k = v
        ff_k = feedforward(v_k, x_pos) if k > 0 else ff0
        u_k = u - ff_k
        if at_rest is not None and abs(v_k) <= moving:
            u_k = at_rest(u, x_pos)
        vl = float(v_lead[k])
        e, v, d = (
            ad[0][0] * e + ad[0][1] * v + ad[0][2] * d + bu[0] * u_k + bl[0] * vl,
            ad[1][0] * e + ad[1][1] * v + ad[1][2] * d + bu[1] * u_k + bl[1] * vl,
            ad[2][0] * e + ad[2][1] * v + ad[2][2] * d + bu[2] * u_k + bl[2] * vl,
        )
        if v < 0.0 <= v_k:
            v = 0.0
        x_pos += 0.5 * (v_k + v) * dt
        speeds.append(v)
    return np.array([e, v, d]), speeds, ff_k, x_pos
