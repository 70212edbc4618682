"""What the controller hands the cycle each period: :class:`ControlOutput`."""

from __future__ import annotations

from dataclasses import dataclass

from truckd.control.estimator import Estimate
from truckd.control.frozen import fast_init


@fast_init
@dataclass(frozen=True)
class ControlOutput:
    """One cycle's command and diagnostics.

    ``u`` the voltage command (V, always finite and within limits); ``u_ff`` its
    feedforward part, ``u_mpc`` the MPC's (or fallback's) part (V); ``mode`` one of
    ``follow``, ``cruise``, ``stop``, ``fallback``, ``hold`` (standstill hold: 0 V, the MPC
    not solved, ``solver_status`` ``not-run``); ``fallback_reason`` None when the MPC
    solved; ``solver_status``, ``solve_iterations``, ``solve_time_s`` (OSQP's own time);
    ``gap_ref`` (m, NaN without lead); the estimate; cumulative counters (``inaccurate``:
    solutions used although OSQP said ``solved inaccurate``); ``disturbance_v`` the
    offset-free action's voltage (V, 0 when off).
    """

    u: float
    u_ff: float
    u_mpc: float
    mode: str
    fallback_reason: str | None
    solver_status: str
    solve_iterations: int
    solve_time_s: float
    gap_ref: float
    estimate: Estimate
    solver_failures: int
    fallback_cycles: int
    overruns: int
    braking_cycles: int
    inaccurate: int = 0
    disturbance_v: float = 0.0
