"""The platoon around the companion cycle: plans in from the predecessor, plan out.

Used by ``truckd run`` (over Zenoh, :class:`DaemonPlatoon`) and by ``truckd sim
--platoon`` (plans passed in simulated time): :func:`follower_inputs` makes the CACC/ACC
decision before a cycle, :func:`cycle_plan` turns the cycle's MPC solution into the plan
to publish after it.  A follower subscribes to exactly one key, its configured
predecessor's ``truckd/<predecessor>/plan``, and refuses plans that name another sender.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

from truckd.control.platoon import (
    Plan,
    PlatoonConfig,
    PlatoonDecision,
    PlatoonMode,
    decode_plan,
    make_plan,
    plan_of_array,
)
from truckd.jsonsafe import json_number
from truckd.runtime.cycle import CompanionCycle, CycleOutputs
from truckd.runtime.platoon_clock import PlanClock


def plan_key(vehicle_id: str) -> str:
    """The Zenoh key of a vehicle's plan (reference section 5)."""
    return f"truckd/{vehicle_id}/plan"


def cycle_plan(
    cyc: CompanionCycle, out: CycleOutputs, t: float, vehicle_id: str = ""
) -> Plan | None:
    """The plan to publish after the cycle ``out``, stamped ``t`` (s, the platoon's shared
    clock): the MPC's predicted speeds when it solved, standstill while the controller
    holds the truck at rest, None otherwise (a fallback has no plan to promise: the
    follower's plan goes stale and it falls back to ACC)."""
    v = cyc.plan_speed_array(out)
    if v is not None:
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


MAX_PLAN_BYTES = 65536
"""A plan payload longer than this is refused undecoded (a 40-step plan is about 2 kB)."""


class _Payload(Protocol):
    def to_bytes(self) -> bytes: ...


class PlanReceiver:
    """The newest valid plan from one predecessor, insulated from the sender's rate.

    :meth:`on_payload` runs on Zenoh's thread for every sample and does constant work:
    it counts the sample and keeps it as the pending one (a ring of one: a pending sample
    not yet decoded is replaced and counted in ``dropped``).  :meth:`latest`, called by
    the loop once per cycle, decodes the pending sample (at most one per call, so at most
    one decode per cycle and key whatever the sender's rate) and returns the newest valid
    plan.  Refused and counted: payloads longer than :data:`MAX_PLAN_BYTES` or that do
    not parse, plans naming another sender, plans stamped more than ``max_skew_s`` in the
    future of ``clock`` (when given: one such plan held would lock out every genuine one
    after it), plans older (by ``seq``) than the one held unless the sender restarted (its
    clock moved on by more than a second).  Thread-safe."""

    def __init__(
        self,
        predecessor: str,
        clock: Callable[[], float] | None = None,
        max_skew_s: float = math.inf,
    ) -> None:
        self.predecessor = predecessor
        self.clock = clock
        self.max_skew_s = max_skew_s
        self.key = plan_key(predecessor)
        self._lock = threading.Lock()
        self._latest: Plan | None = None
        self._pending: bytes | _Payload | None = None
        self.received = 0
        """Samples that arrived on the key (every one, also those dropped)."""
        self.decoded = 0
        """Samples decoded (at most one per :meth:`latest` call)."""
        self.accepted = 0
        self.refused = 0
        self.last_error = ""
        self.blocked = False
        """Injected link loss (HIL runs): every plan is dropped while set."""
        self.dropped = 0
        """Samples never decoded: replaced by a newer one before the loop took it, or
        received while the link was blocked."""

    def on_payload(self, payload: bytes | _Payload) -> None:
        """One sample arrived (Zenoh's thread): constant work, no decoding."""
        with self._lock:
            self.received += 1
            if self.blocked:
                self.dropped += 1
                return
            if self._pending is not None:
                self.dropped += 1
            self._pending = payload

    def _take(self) -> None:
        with self._lock:
            raw, self._pending = self._pending, None
        if raw is None:
            return
        self.decoded += 1
        try:
            data = raw if isinstance(raw, bytes) else raw.to_bytes()
            if len(data) > MAX_PLAN_BYTES:
                raise ValueError(f"{len(data)} bytes, more than {MAX_PLAN_BYTES}")
            plan = decode_plan(data)
        except Exception as exc:  # any payload at all: nested too deep, not UTF-8, ...
            self.refused += 1
            self.last_error = str(exc)[:200] or type(exc).__name__
            return
        if plan.vehicle_id and plan.vehicle_id != self.predecessor:
            self.refused += 1
            self.last_error = f"plan from {plan.vehicle_id!r}, expected {self.predecessor!r}"
            return
        ahead = plan.t - self.clock() if self.clock is not None else -math.inf
        if ahead > self.max_skew_s:
            self.refused += 1
            self.last_error = f"plan stamped {ahead:.3f} s in the future"
            return
        with self._lock:
            old = self._latest
            if old is None or plan.seq > old.seq or plan.t > old.t + 1.0:
                self._latest = plan
                self.accepted += 1
                return
        self.refused += 1
        self.last_error = f"plan seq {plan.seq} not newer than the one held ({old.seq})"

    def latest(self) -> Plan | None:
        """Decode the pending sample, if any (one at most), and return the newest valid
        plan (the loop's side: call it once per cycle)."""
        self._take()
        with self._lock:
            return self._latest


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
    """``truckd run``'s platoon part.  Every truck publishes its plan each cycle; a truck
    with ``platoon.predecessor`` set also follows that truck's plan (CACC/ACC).  Plans are
    stamped with ``wall()`` (the system clock); with ``platoon.clock_sync`` the
    predecessor's clock offset and drift are estimated from its plans and each plan is
    aged on this truck's clock (:mod:`truckd.runtime.platoon_clock`), so the clocks need
    not agree."""

    def __init__(
        self,
        vehicle_id: str,
        cfg: PlatoonConfig,
        cyc: CompanionCycle,
        wall: Callable[[], float] = time.time,
    ) -> None:
        self.vehicle_id = vehicle_id
        self.cfg = cfg
        self.cyc = cyc
        self.wall = wall
        self.receiver = (  # clock_sync: plans are aged on this clock after the receiver
            PlanReceiver(cfg.predecessor, None if cfg.clock_sync else wall, cfg.max_clock_skew_s)
            if cfg.predecessor
            else None
        )
        self.clock = PlanClock()
        self.mode = (
            PlatoonMode(cfg, cyc.period, cyc.controller.forecast_steps) if cfg.predecessor else None
        )
        self.decision: PlatoonDecision | None = None
        self._now = math.nan
        self._rate_mark = (math.nan, 0)  # (wall time, plans received) at the last health
        self.plan_rate_hz: float | None = None
        """Plans received per second since the previous health message (None: unknown)."""

    def limit_ingress(self, limit: Callable[[str, float], None]) -> None:
        """Cap the predecessor's plan key at :data:`INGRESS_FACTOR` plans per control
        period in the session (``limit(key, hz)``, before the session opens)."""
        if self.receiver is not None:
            limit(self.receiver.key, INGRESS_FACTOR / self.cyc.period)

    def subscribe(
        self,
        subscribe_key: Callable[[str, Callable[[bytes], None]], None],
        fault_injection: bool = False,
        subscribe_raw: Callable[[str, Callable[[Any], None]], None] | None = None,
    ) -> None:
        """Subscribe to the predecessor's plan key only (nothing for a leading truck),
        with ``subscribe_raw`` when given (the payload passed uncopied); with
        ``fault_injection`` also to ``truckd/<vehicle_id>/platoon_fault`` (HIL runs:
        ``{"link": "down"}`` drops every plan received until ``{"link": "up"}``)."""
        if self.receiver is not None:
            (subscribe_raw or subscribe_key)(self.receiver.key, self.receiver.on_payload)
            if fault_injection:
                subscribe_key(f"truckd/{self.vehicle_id}/platoon_fault", self.apply_fault)

    def apply_fault(self, payload: bytes) -> None:
        """An injected link fault (see :meth:`subscribe`); anything else is ignored."""
        try:
            cmd = json.loads(payload)
        except ValueError:
            return
        if (
            self.receiver is not None
            and isinstance(cmd, dict)
            and cmd.get("link") in ("down", "up")
        ):
            self.receiver.blocked = cmd["link"] == "down"

    def decide(self, last: CycleOutputs | None) -> PlatoonDecision | None:
        """Before the cycle: the forecast and headway (None for a leading truck)."""
        self._now = self.wall()
        if self.mode is None or self.receiver is None:
            return None
        plan = self.receiver.latest()
        if self.cfg.clock_sync:  # the predecessor's clock is not ours (platoon_clock.py)
            self.clock.observe_latest(plan, self._now)
            plan = self.clock.to_own(plan)
        self.decision = follower_inputs(self.mode, self._now, plan, last, self.cyc.control_cfg.d_0)
        return self.decision

    def plan_message(self, out: CycleOutputs) -> dict[str, Any] | None:
        """After the cycle: the plan to publish (None when there is none this cycle)."""
        t = self._now if math.isfinite(self._now) else self.wall()
        p = cycle_plan(self.cyc, out, t, self.vehicle_id)
        return replace(p, predecessor=self.cfg.predecessor).as_dict() if p is not None else None

    def health(self) -> dict[str, Any]:
        """The ``platoon`` entry of the health message."""
        d, r, m = self.decision, self.receiver, self.mode
        age = d.plan_age_s if d is not None else math.nan
        if r is not None:
            now, (t_mark, n_mark) = self.wall(), self._rate_mark
            if now - t_mark > 0.2:  # NaN at the first call: no rate yet
                self.plan_rate_hz = (r.received - n_mark) / (now - t_mark)
            if not now - t_mark <= 0.2:
                self._rate_mark = (now, r.received)
        rate = self.plan_rate_hz
        return {
            "predecessor": self.cfg.predecessor or None,
            "mode": d.mode if d is not None else None,
            "headway_s": d.headway if d is not None else None,
            "plan_age_s": json_number(age),
            "plans_accepted": r.accepted if r is not None else 0,
            "plans_refused": r.refused if r is not None else 0,
            "plans_dropped": r.dropped if r is not None else 0,
            "plans_received": r.received if r is not None else 0,
            "plan_rate_hz": rate,
            "plan_flood": rate is not None and rate > FLOOD_FACTOR / self.cyc.period,
            "switches": m.switches if m is not None else 0,
            "plans_disagreeing": m.disagreements if m is not None else 0,
        }
