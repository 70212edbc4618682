"""The platoon around the companion cycle: plans in from the predecessor, plan out.

Used by ``truckd run`` (over Zenoh, :class:`DaemonPlatoon`) and by ``truckd sim
--platoon`` (plans passed in simulated time): :func:`follower_inputs` makes the CACC/ACC
decision before a cycle, :func:`cycle_plan` turns the cycle's MPC solution into the plan
to publish after it.  With ``platoon.order: fixed`` a follower subscribes to exactly one
key, its configured predecessor's ``truckd/<predecessor>/plan`` (:mod:`.plan_receiver`),
and refuses plans that name another sender; with ``auto`` it hears every truck's
(:mod:`.plan_hearing`) and finds whom to follow (:mod:`.platoon_follow`).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from truckd.control.estimator import Estimate
from truckd.control.platoon import (
    Plan,
    PlatoonConfig,
    PlatoonDecision,
    PlatoonMode,
    make_plan,
    plan_of_array,
)
from truckd.jsonsafe import json_number
from truckd.runtime.cycle import CompanionCycle, CycleOutputs
from truckd.runtime.plan_hearing import MAX_SENDERS, PlanHearing
from truckd.runtime.plan_receiver import MAX_PLAN_BYTES, PlanReceiver, plan_key
from truckd.runtime.platoon_follow import Follow, PlanSource
from truckd.runtime.platoon_join import JoinOrders, join_key

__all__ = [
    "MAX_PLAN_BYTES",
    "DaemonPlatoon",
    "PlanReceiver",
    "cycle_plan",
    "follower_inputs",
    "plan_key",
    "platoon_state_fields",
]

log = logging.getLogger(__name__)


def cycle_plan(
    cyc: CompanionCycle, out: CycleOutputs, t: float, vehicle_id: str = ""
) -> Plan | None:
    """The plan to publish after the cycle ``out``, stamped ``t`` (s, the platoon's shared
    clock): the MPC's predicted speeds when it solved, standstill while the controller
    holds the truck at rest, None otherwise (a fallback has no plan to promise: the
    follower's plan goes stale and it falls back to ACC)."""
    v = cyc.plan_speed_array(out)
    if v is not None:
        compiled = cyc.compiled_plan(v)
        if compiled is not None:  # speeds and accelerations made by the compiled cycle
            n = len(compiled) // 2
            v_plan, a_plan = tuple(compiled[:n]), tuple(compiled[n:])
            return Plan(t, out.seq, cyc.period, v_plan, a_plan, vehicle_id)
        return plan_of_array(t, out.seq, cyc.period, v, vehicle_id)
    c = out.control
    if c is not None and c.mode == "hold":
        n = cyc.controller.mpc.horizon
        return make_plan(t, out.seq, cyc.period, [0.0] * (n + 1), vehicle_id)
    return None


def follower_inputs(
    mode: PlatoonMode, now: float, plan: Plan | None, last: CycleOutputs | None, d_0: float
) -> PlatoonDecision:
    """The platoon part of a follower's cycle, before the step: the CACC/ACC decision
    from the latest plan received (``now`` on the platoon's shared clock, s), with the
    previous cycle's estimate (``last``) for the time gap actually driven (``d_0`` the
    standstill gap, m) and the lead speed the range sensor measures (a plan that disagrees
    with it is not followed)."""
    est = last.control.estimate if last is not None and last.control is not None else None
    return mode.update(
        now,
        plan,
        est.v if est is not None and est.speed_valid else math.nan,
        est.gap if est is not None and est.lead_valid else math.nan,
        d_0,
        est.v_lead if est is not None and est.lead_valid else math.nan,
        est.v_lead_std if est is not None and est.lead_valid else math.nan,
    )


def platoon_state_fields(d: PlatoonDecision | None) -> dict[str, Any]:
    """Merged into the state message: ``platoon`` CACC/ACC (None: not following) and the
    headway driven (s), of the cycle's decision ``d``."""
    return {
        "platoon": d.mode if d is not None else None,
        "headway": d.headway if d is not None else None,
    }


INGRESS_FACTOR = 4.0
"""At most this many plans per control period are let into the daemon's Zenoh session on
the predecessor's key (Zenoh's ingress downsampling drops the rest before any Python
runs): a predecessor publishes one per cycle; a sender's jitter fits."""

FLOOD_FACTOR = 2.0
"""Plans arriving faster than this many per control period are a flood (a predecessor
publishes one per cycle; a flood arrives at the ingress limit): ``plan_flood`` in health,
shown by ``truckd monitor``."""


class DaemonPlatoon:
    """``truckd run``'s platoon part.  Every truck publishes its plan each cycle.  With
    ``platoon.order: fixed`` a truck with ``platoon.predecessor`` set follows that truck's
    plan (CACC/ACC) and subscribes to that key only.  With ``auto`` it hears every truck's
    plan (``truckd/*/plan``) and follows whom the order finds (:mod:`.platoon_follow`:
    the tail when ``predecessor`` is empty, the truck that joins in front of it, the
    predecessor's predecessor when that one leaves), decided between each cycle's
    estimate and its control law.  Plans are stamped with ``wall()`` (the system clock);
    with ``platoon.clock_sync`` each sender's clock offset and drift are estimated from
    its plans and each plan is aged on this truck's clock
    (:mod:`truckd.runtime.platoon_clock`), so the clocks need not agree."""

    def __init__(
        self,
        vehicle_id: str,
        cfg: PlatoonConfig,
        cyc: CompanionCycle,
        wall: Callable[[], float] = time.time,
        mono: Callable[[], float] = time.monotonic,
    ) -> None:
        """``wall``: the clock plans are stamped and aged on (the system clock); ``mono``:
        the order's own times (who was heard since when), which no clock step may move."""
        self.vehicle_id = vehicle_id
        self.mono = mono
        self.cfg = cfg
        self.cyc = cyc
        self.wall = wall
        self.auto = cfg.order == "auto"
        self._skew_clock = None if cfg.clock_sync else wall  # else aged after the receiver
        self._fixed = (
            PlanReceiver(cfg.predecessor, self._skew_clock, cfg.max_clock_skew_s)
            if cfg.predecessor and not self.auto
            else None
        )
        self._source = PlanSource(cfg.predecessor)
        """The fixed predecessor's newest plan and clock (with the auto order: the
        follower's own sources, :attr:`follow`)."""
        self.mode = (
            PlatoonMode(cfg, cyc.period, cyc.controller.forecast_steps)
            if cfg.predecessor or self.auto
            else None
        )
        self.decision: PlatoonDecision | None = None
        self._now = math.nan
        self._rate_mark = (math.nan, 0)  # (wall time, plans received) at the last health
        self.plan_rate_hz: float | None = None
        """Plans received per second since the previous health message (None: unknown)."""
        self.hearing = (
            PlanHearing(vehicle_id, cfg.predecessor, self._skew_clock, cfg.max_clock_skew_s)
            if self.auto
            else None
        )
        """``platoon.order: auto``: every sender's plans (None with a fixed order)."""
        self.errors = 0
        """Cycles whose platoon decision raised (the truck then drives ACC); ``last_error``."""
        self.last_error = ""
        self._settled = False
        self.joins = JoinOrders(vehicle_id)
        """Operators' join orders (``truckd/<id>/platoon_join``, with the auto order)."""
        self.follow: Follow | None = None
        if self.auto and self.mode is not None:
            self.follow = Follow(
                vehicle_id, cfg.predecessor, self.mode, cyc.control_cfg.d_0, mono()
            )
            cyc.controller.redecide = self._on_estimate

    @property
    def receiver(self) -> PlanReceiver | None:
        """The receiver of the truck followed now (None: none)."""
        if self.follow is None or self.hearing is None:
            return self._fixed
        return self.hearing.receivers.get(self.follow.predecessor)

    @property
    def predecessor(self) -> str:
        """The vehicle id followed now ("": none)."""
        return self.follow.predecessor if self.follow is not None else self.cfg.predecessor

    def limit_ingress(self, limit: Callable[[str, float], None]) -> None:
        """Cap the predecessor's plan key at :data:`INGRESS_FACTOR` plans per control
        period in the session (``limit(key, hz)``, before the session opens); with the
        auto order every sender's plans together at that times :data:`MAX_SENDERS` (Zenoh's
        rule counts every key it matches together)."""
        if self._fixed is not None:
            limit(self._fixed.key, INGRESS_FACTOR / self.cyc.period)
        elif self.auto:
            limit(plan_key("*"), INGRESS_FACTOR * MAX_SENDERS / self.cyc.period)

    def subscribe(
        self,
        subscribe_key: Callable[[str, Callable[[bytes], None]], None],
        fault_injection: bool = False,
        subscribe_raw: Callable[[str, Callable[[Any], None]], None] | None = None,
        subscribe_keyed: Callable[[str, Callable[[str, Any], None]], None] | None = None,
    ) -> None:
        """Subscribe to the predecessor's plan key only (nothing for a leading truck),
        with ``subscribe_raw`` when given (the payload passed uncopied); with the auto
        order to every plan (``subscribe_keyed``: the callback gets the sample's key and
        payload) and to the operators' join orders (:mod:`.platoon_join`); with
        ``fault_injection`` also to ``truckd/<vehicle_id>/platoon_fault``
        (HIL runs: ``{"link": "down"}`` drops every plan received until ``{"link":
        "up"}``)."""
        following = self._fixed is not None or self.auto
        if self._fixed is not None:
            (subscribe_raw or subscribe_key)(self._fixed.key, self._fixed.on_payload)
        elif self.auto:
            if subscribe_keyed is None:
                raise ValueError("the auto order needs a subscription that passes the key")
            assert self.hearing is not None
            subscribe_keyed(plan_key("*"), self.hearing.on_sample)
        if self.auto:
            subscribe_key(join_key(self.vehicle_id), self.joins.on_payload)
        if following and fault_injection:
            subscribe_key(f"truckd/{self.vehicle_id}/platoon_fault", self.apply_fault)

    def apply_fault(self, payload: bytes) -> None:
        """An injected link fault (see :meth:`subscribe`); anything else is ignored."""
        try:
            cmd = json.loads(payload)
        except ValueError:
            return
        if not (isinstance(cmd, dict) and cmd.get("link") in ("down", "up")):
            return
        blocked = cmd["link"] == "down"
        if self._fixed is not None:
            self._fixed.blocked = blocked
        if self.hearing is not None:
            self.hearing.block(blocked)

    def decide(self, last: CycleOutputs | None) -> PlatoonDecision | None:
        """Before the cycle: the forecast and headway (None for a leading truck with a
        fixed order).  Whatever the plans held, it returns: a decision that raised
        (counted in :attr:`errors`) is ACC on the range sensor, the headway ramped."""
        self._now = self.wall()
        if self.mode is None:
            return None
        d_0 = self.cyc.control_cfg.d_0
        try:
            if self.follow is not None and self.hearing is not None:
                self.hearing.hear(self.follow, self._now, self.mono(), self._settled)
                source = self.follow.source
            else:
                assert self._fixed is not None
                source = self._source
                newest = self._fixed.latest()
                if newest is not None:
                    source.hold_latest(newest, self._now)
            # on this truck's clock: the predecessor's is not ours (platoon_clock.py)
            plan = source.on_own_clock(self.cfg.clock_sync)
            self.decision = follower_inputs(self.mode, self._now, plan, last, d_0)
        except Exception as exc:  # the loop goes on, on the range sensor
            self._failed(exc)
            self.decision = follower_inputs(self.mode, self._now, None, last, d_0)
        return self.decision

    def _failed(self, exc: Exception) -> None:
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"[:200]
        if self.errors == 1 or self.errors % 500 == 0:
            log.warning("platoon decision failed (%d so far): %s", self.errors, self.last_error)

    def _on_estimate(self, est: Estimate) -> tuple[list[float] | None, float] | None:
        """Between the cycle's estimate and its control law (auto order): another truck
        ahead gives this cycle's forecast and headway again (an error: no change)."""
        f, hearing = self.follow, self.hearing
        if f is None or hearing is None or self.decision is None:
            return None
        try:
            return self._order_step(f, hearing, est, self.decision)
        except Exception as exc:  # the loop goes on with the decision made
            self._failed(exc)
            return None

    def _order_step(
        self, f: Follow, hearing: PlanHearing, est: Estimate, decision: PlatoonDecision
    ) -> tuple[list[float] | None, float] | None:
        n_events = len(f.events)
        gap = est.gap if est.lead_valid else None
        v_lead = est.v_lead if est.lead_valid else math.nan
        mono = self.mono()
        # a tail is taken once the plans have been heard for cacc_return_s; trucks heard
        # naming this truck's predecessor before then were there first (not joiners)
        settled = mono - hearing.first_heard >= self.cfg.cacc_return_s
        if settled and not self._settled:
            self._settled = True
            f.pred_since = max(f.pred_since, mono)
        told, behind = self.joins.take()  # an operator's order first, then the order's rules
        moved = told and f.told(behind, gap, est.v, mono)
        changed = f.step(gap, est.v, v_lead, hearing.heard, mono, settled, est.v_lead_std)
        changed = changed or moved
        for _t, what in f.events[n_events:]:
            log.info("platoon: %s", what)
        if not changed:
            return None
        fc, headway = f.redecide(self.cfg.clock_sync, self._now)
        self.decision = replace(decision, mode=f.mode.mode, headway=headway, forecast=fc)
        return fc, headway

    def plan_message(self, out: CycleOutputs) -> dict[str, Any] | None:
        """After the cycle: the plan to publish (None when there is none this cycle)."""
        t = self._now if math.isfinite(self._now) else self.wall()
        p = cycle_plan(self.cyc, out, t, self.vehicle_id)
        return replace(p, predecessor=self.predecessor).as_dict() if p is not None else None

    def health(self) -> dict[str, Any]:
        """The ``platoon`` entry of the health message."""
        d, r, m = self.decision, self.receiver, self.mode
        age = d.plan_age_s if d is not None else math.nan
        hearing = self.hearing
        received = hearing.received if hearing is not None else (r.received if r is not None else 0)
        if m is not None:
            now, (t_mark, n_mark) = self.wall(), self._rate_mark
            if now - t_mark > 0.2:  # NaN at the first call: no rate yet
                self.plan_rate_hz = (received - n_mark) / (now - t_mark)
            if not now - t_mark <= 0.2:
                self._rate_mark = (now, received)
        rate = self.plan_rate_hz
        senders = max(1, len(hearing.receivers)) if hearing is not None else 1
        out: dict[str, Any] = {
            "predecessor": self.predecessor or None,
            "mode": d.mode if d is not None else None,
            "headway_s": d.headway if d is not None else None,
            "plan_age_s": json_number(age),
            "plans_accepted": r.accepted if r is not None else 0,
            "plans_refused": r.refused if r is not None else 0,
            "plans_dropped": r.dropped if r is not None else 0,
            "plans_received": received,
            "plan_rate_hz": rate,
            "plan_flood": rate is not None and rate > senders * FLOOD_FACTOR / self.cyc.period,
            "switches": m.switches if m is not None else 0,
            "plans_disagreeing": m.disagreements if m is not None else 0,
            "errors": self.errors,
        }
        if self.follow is not None and hearing is not None:
            ev = self.follow.events
            out["order"] = {
                "standby": self.follow.standby.sender or None,
                "senders": sorted(hearing.receivers),
                "senders_refused": hearing.senders_refused,
                "changes": len(ev),
                "last_change": ev[-1][1] if ev else None,
                "alone": self.follow.alone,
                "joins_told": self.joins.told,
                "joins_refused": self.joins.refused,
                "last_join": self.joins.last or None,
            }
        return out
