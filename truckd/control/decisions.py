"""The controller's decisions between the estimate and the solve: the standstill hold, the
MPC's mode and the offset-free action's disturbance estimate.  Pure functions of the
configuration, the estimate and the state passed in (no I/O, no clock): the Python
reference of the decisions the compiled cycle takes in the same call as the estimator's
update and the solve (``decide`` in truckd/control/kernel/cycle_numerics.c; its hold only
begins in Python, and a hold in progress is Python's throughout).
"""

from __future__ import annotations

import math

from truckd.control.config import ControlConfig
from truckd.control.estimator import Estimate

SATURATED_V = 0.01
"""A command this close to the driver's limit (V, the QP's accuracy) is at the limit."""


def hold_update(
    cfg: ControlConfig, holding: bool, release_cycles: int, est: Estimate, v: float, lead: bool
) -> tuple[bool, int]:
    """Standstill hold, as an ACC holds the car behind a stopped lead: whether it holds
    after this cycle and the release count (``v`` the own speed, m/s; ``lead``: a lead is
    tracked with a finite gap and speed).

    Entered at rest (``|v| <= moving_speed``) behind a lead no faster than
    ``hold_lead_speed`` with the gap at most ``d_0 + hold_gap_tol``; left only when the
    lead is faster than ``hold_release_speed`` or the gap exceeds ``d_0 +
    hold_release_gap`` (both above the entry thresholds) for ``hold_release_cycles``
    consecutive cycles (the lead-speed estimate is noisy at rest): no chatter.  A lead
    lost while holding keeps the hold: it was last seen stopped just ahead.
    """
    if holding:
        going = lead and (
            est.v_lead > cfg.hold_release_speed or est.gap > cfg.d_0 + cfg.hold_release_gap
        )
        release_cycles = release_cycles + 1 if going else 0
        if release_cycles >= cfg.hold_release_cycles:
            return False, 0
        return True, release_cycles
    entered = (
        lead
        and abs(v) <= cfg.moving_speed
        and est.v_lead <= cfg.hold_lead_speed
        and est.gap <= cfg.d_0 + cfg.hold_gap_tol
    )
    return entered, release_cycles


def mode_of(cfg: ControlConfig, est: Estimate, lead: bool, gap_ref: float) -> tuple[str, float]:
    """The MPC's mode and speed reference (m/s): follow a lead that is near and either
    slower than the set speed or too close (``gap_ref`` m); otherwise cruise at the set
    speed (the minimum gap is still a constraint), or stop without a lead when so
    configured."""
    near = lead and est.gap - gap_ref < cfg.follow_window
    if near and (est.v_lead <= cfg.v_set or est.gap < gap_ref):
        return "follow", cfg.v_set
    if lead or cfg.on_lead_lost == "cruise":
        return "cruise", cfg.v_set
    return "stop", 0.0


def disturbance_update(
    cfg: ControlConfig,
    disturbance: float,
    expected: float,
    v: float,
    limited: bool,
    wanted: float,
    u_max: float,
    u_hi: float,
    b_v: float,
) -> float:
    """Offset-free action (``disturbance_gain`` > 0): the voltage the model lacks (V).

    The speed the last plan expected now (``expected``, m/s; NaN: none) minus the speed
    measured (``v``), divided by the model's speed-per-volt over one step (``b_v``,
    m/s/V), is an input-voltage disturbance; a slow integrator (gain per cycle) estimates
    it and the feedforward adds it.  Frozen at rest (stiction, not a disturbance), after
    fallbacks (no plan expected anything) and while the last command was at the driver's
    limit (``limited``: cut to its current limit; ``wanted`` V within ``SATURATED_V`` of
    ``-u_max`` or ``u_hi``, V): no wind-up.
    """
    gain = cfg.disturbance_gain
    if (
        gain > 0.0
        and not limited
        and math.isfinite(expected)
        and abs(v) > cfg.moving_speed
        and -u_max + SATURATED_V < wanted < u_hi - SATURATED_V
    ):
        disturbance += gain * (expected - v) / b_v
        limit = cfg.disturbance_max
        disturbance = min(max(disturbance, -limit), limit)
    return disturbance
