"""A predecessor's plans on the receiver's own clock.

Plans are stamped on the sender's clock; no truck assumes that clocks agree.
:class:`PlanClock` notes each plan's arrival on the receiver's clock, estimates the
sender's clock offset and drift from those pairs
(:class:`~truckd.control.clocksync.ClockEstimator`) and gives the plan back restamped on
the receiver's clock, so its age, freshness and forecast are all judged on one clock.
Used by ``truckd sim --platoon`` (arrival at delivery) and by the daemon (arrival at the
first cycle that sees the plan: up to one period late, which the estimator's lower
envelope mostly removes).
"""

from __future__ import annotations

from dataclasses import replace

from truckd.control.clocksync import ClockEstimator
from truckd.control.platoon import Plan


class PlanClock:
    """One predecessor's clock (see the module docstring)."""

    def __init__(self) -> None:
        self.estimator = ClockEstimator()
        self._seen: tuple[str, int, float] | None = None

    def reset(self) -> None:
        """Another predecessor: its clock is another clock."""
        self.estimator.reset()
        self._seen = None

    def observe(self, plan: Plan, arrived: float) -> None:
        """``plan`` arrived at ``arrived`` (s, the receiver's clock)."""
        self.estimator.observe(plan.t, arrived)

    def observe_latest(self, plan: Plan | None, now: float) -> None:
        """The daemon's way: the newest plan held, noted once, arrived by ``now``."""
        if plan is None:
            return
        key = (plan.vehicle_id, plan.seq, plan.t)
        if key != self._seen:
            self._seen = key
            self.observe(plan, now)

    def to_own(self, plan: Plan | None) -> Plan | None:
        """``plan`` stamped on the receiver's clock (its ``dt`` scaled by the drift);
        None before any plan was observed."""
        est = self.estimator.estimate
        if plan is None or est is None:
            return None
        return replace(plan, t=est.to_own(plan.t), dt=plan.dt * (1.0 + est.drift))
