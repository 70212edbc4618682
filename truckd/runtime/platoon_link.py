"""The platoon around the companion cycle: plans in from the predecessor, plan out.

Used by ``truckd run`` (over Zenoh, :class:`DaemonPlatoon`) and by ``truckd sim
--platoon`` (plans passed in simulated time): :func:`follower_inputs` makes the CACC/ACC
decision before a cycle, :func:`cycle_plan` turns the cycle's MPC solution into the plan
to publish after it.  A follower subscribes to exactly one key, its configured
predecessor's ``truckd/<predecessor>/plan``, and refuses plans that name another sender.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, Protocol

from truckd.control.estimator import Estimate
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
from truckd.runtime.platoon_follow import Follow, HeardPlans

log = logging.getLogger(__name__)


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

    def _take(self, max_bytes: int = MAX_PLAN_BYTES) -> None:
        with self._lock:
            raw, self._pending = self._pending, None
        if raw is None:
            return
        self.decoded += 1
        try:
            data = raw if isinstance(raw, bytes) else raw.to_bytes()
            if len(data) > max_bytes:
                raise ValueError(f"{len(data)} bytes, more than {max_bytes}")
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

    def latest(self, max_bytes: int = MAX_PLAN_BYTES) -> Plan | None:
        """Decode the pending sample, if any (one at most; refused when longer than
        ``max_bytes``), and return the newest valid plan (the loop's side: call it once
        per cycle)."""
        self._take(max_bytes)
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


HEAR_OTHERS_EVERY = 10
"""``platoon.order: auto`` while following: another sender's plan is decoded once every
this many cycles, in turn (a decode costs about 30 us; the chain changes when a truck
announces a join, long before it moves in): with 10 trucks each is heard every second."""

MAX_SENDERS = 32
"""``platoon.order: auto``: plans are heard from at most this many trucks (the first
heard, and always the configured predecessor, the one followed and the standby); samples
from more are dropped and counted (``senders_refused`` in health); a sender silent for
:data:`SILENT_S` is forgotten, making room."""

SILENT_S = 4.0
"""s: a sender heard from no sample this long is forgotten (its receiver and what its
plans said of the order), unless configured or followed: five ``plan_hold_s``."""

OTHER_PLAN_BYTES = 16384
"""Plans of senders neither followed nor the standby are decoded up to this size only (a
plan of 40 steps is about 2 kB, of the configuration's longest horizon about 20 kB: such
a truck is heard once it is the standby); a decode of 64 kB costs about 2.4 ms."""

SEARCH_DECODES = 4
"""Senders decoded per cycle, in turn, while no predecessor is followed (the tail search)."""


def plan_sender(key: str) -> str | None:
    """The vehicle id of a plan key ``truckd/<id>/plan``; None for any other key."""
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "truckd" and parts[2] == "plan" and parts[1]:
        return parts[1]
    return None


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
        self.clock = PlanClock()
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
        # platoon.order auto: every sender's receiver, the plans heard, whom to follow
        self.receivers: dict[str, PlanReceiver] = {}
        self._receivers_lock = threading.Lock()
        self._blocked = False
        self.senders_refused = 0
        """Samples from senders beyond :data:`MAX_SENDERS` (dropped)."""
        self.heard = HeardPlans()
        self._heard_next = 0
        self._wanted: frozenset[str] = frozenset({cfg.predecessor} - {""})
        """Senders always admitted: the configured predecessor, the one followed, the
        standby (written by the loop, read by Zenoh's thread: one reference swapped)."""
        self._activity: dict[str, tuple[int, float]] = {}
        """Per sender: samples received and when that count last changed (monotonic s)."""
        self.errors = 0
        """Cycles whose platoon decision raised (the truck then drives ACC); ``last_error``."""
        self.last_error = ""
        self._first_heard = math.nan
        """When the first plan of another truck was heard (s, NaN: none yet)."""
        self._settled = False
        self.follow: Follow | None = None
        if self.auto and self.mode is not None:
            self.follow = Follow(
                vehicle_id, cfg.predecessor, self.mode, cyc.control_cfg.d_0, mono()
            )
            cyc.controller.redecide = self._on_estimate

    @property
    def receiver(self) -> PlanReceiver | None:
        """The receiver of the truck followed now (None: none)."""
        if self.follow is None:
            return self._fixed
        return self.receivers.get(self.follow.predecessor) if self.follow.predecessor else None

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
        payload); with ``fault_injection`` also to ``truckd/<vehicle_id>/platoon_fault``
        (HIL runs: ``{"link": "down"}`` drops every plan received until ``{"link":
        "up"}``)."""
        following = self._fixed is not None or self.auto
        if self._fixed is not None:
            (subscribe_raw or subscribe_key)(self._fixed.key, self._fixed.on_payload)
        elif self.auto:
            if subscribe_keyed is None:
                raise ValueError("the auto order needs a subscription that passes the key")
            subscribe_keyed(plan_key("*"), self.on_sample)
        if following and fault_injection:
            subscribe_key(f"truckd/{self.vehicle_id}/platoon_fault", self.apply_fault)

    def on_sample(self, key: str, payload: bytes | _Payload) -> None:
        """A plan sample on ``key`` (auto order, Zenoh's thread): handed to its sender's
        receiver (made at the sender's first sample); constant work, no decoding."""
        sender = plan_sender(key)
        if sender is None or sender == self.vehicle_id:
            return
        r = self.receivers.get(sender)
        if r is None:
            with self._receivers_lock:
                r = self.receivers.get(sender)
                if r is None:
                    if len(self.receivers) >= MAX_SENDERS and sender not in self._wanted:
                        self.senders_refused += 1
                        return
                    r = PlanReceiver(sender, self._skew_clock, self.cfg.max_clock_skew_s)
                    r.blocked = self._blocked
                    self.receivers = {**self.receivers, sender: r}  # readers see old or new
        r.on_payload(payload)

    def apply_fault(self, payload: bytes) -> None:
        """An injected link fault (see :meth:`subscribe`); anything else is ignored."""
        try:
            cmd = json.loads(payload)
        except ValueError:
            return
        if not (isinstance(cmd, dict) and cmd.get("link") in ("down", "up")):
            return
        self._blocked = cmd["link"] == "down"
        with self._receivers_lock:
            for r in [self._fixed, *self.receivers.values()]:
                if r is not None:
                    r.blocked = self._blocked

    def decide(self, last: CycleOutputs | None) -> PlatoonDecision | None:
        """Before the cycle: the forecast and headway (None for a leading truck with a
        fixed order).  Whatever the plans held, it returns: a decision that raised
        (counted in :attr:`errors`) is ACC on the range sensor, the headway ramped."""
        self._now = self.wall()
        if self.mode is None:
            return None
        d_0 = self.cyc.control_cfg.d_0
        try:
            if self.follow is not None:
                plan = self._hear(self.follow, self._now, self.mono())
            else:
                assert self._fixed is not None
                plan = self._fixed.latest()
                if self.cfg.clock_sync:  # the predecessor's clock is not ours
                    self.clock.observe_latest(plan, self._now)
                    plan = self.clock.to_own(plan)
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

    def _hear(self, f: Follow, now: float, mono: float) -> Plan | None:
        """Auto order: the newest plans of the predecessor and the standby (each cycle)
        and of one other sender in turn every :data:`HEAR_OTHERS_EVERY` cycles (while no
        predecessor is followed, or the plans are not yet heard for ``cacc_return_s``,
        :data:`SEARCH_DECODES` senders each cycle), noted in
        :attr:`heard` (at ``mono``, the order's clock); senders silent for
        :data:`SILENT_S` forgotten; the predecessor's plan on this truck's clock (``now``,
        s)."""
        receivers = self.receivers
        if receivers and math.isnan(self._first_heard):
            self._first_heard = mono
        mine = (f.source.sender, f.standby.sender)
        self._wanted = frozenset({self.cfg.predecessor, *mine} - {""})
        for src in (f.source, f.standby):
            r = receivers.get(src.sender) if src.sender else None
            if r is not None:
                plan = r.latest()
                if plan is not None:
                    src.hold_latest(plan, now)
                    self.heard.note(src.sender, plan, mono)
        self._heard_next += 1
        k, turn = divmod(self._heard_next, HEAR_OTHERS_EVERY)
        if not turn:
            self._forget_silent(mono)
            receivers = self.receivers
        others = [v for v in receivers if v not in mine]
        if others and f.predecessor and self._settled:  # one every HEAR_OTHERS_EVERY cycles
            others = [] if turn else [others[k % len(others)]]
        elif len(others) > SEARCH_DECODES:  # searching or settling: every sender soon
            k = self._heard_next * SEARCH_DECODES
            others = [others[(k + i) % len(others)] for i in range(SEARCH_DECODES)]
        for vid in others:
            plan = receivers[vid].latest(OTHER_PLAN_BYTES)
            if plan is not None:
                self.heard.note(vid, plan, mono)
        return f.source.on_own_clock(self.cfg.clock_sync)

    def _forget_silent(self, mono: float) -> None:
        """Senders with no sample for :data:`SILENT_S` are forgotten, but for the
        configured predecessor and the one followed (a silent standby is forgotten: an
        announced joiner that fell silent no longer holds the room open)."""
        kept = {self.cfg.predecessor, self.predecessor}
        gone = []
        for vid, r in self.receivers.items():
            count, since = self._activity.get(vid, (-1, mono))
            if r.received != count:
                self._activity[vid] = (r.received, mono)
            elif mono - since >= SILENT_S and vid not in kept:
                gone.append(vid)
        if gone:
            with self._receivers_lock:
                self.receivers = {v: r for v, r in self.receivers.items() if v not in gone}
            for vid in gone:
                self._activity.pop(vid, None)
                self.heard.forget(vid)

    def _on_estimate(self, est: Estimate) -> tuple[list[float] | None, float] | None:
        """Between the cycle's estimate and its control law (auto order): another truck
        ahead gives this cycle's forecast and headway again (an error: no change)."""
        f = self.follow
        if f is None or self.decision is None:
            return None
        try:
            return self._order_step(f, est, self.decision)
        except Exception as exc:  # the loop goes on with the decision made
            self._failed(exc)
            return None

    def _order_step(
        self, f: Follow, est: Estimate, decision: PlatoonDecision
    ) -> tuple[list[float] | None, float] | None:
        n_events = len(f.events)
        gap = est.gap if est.lead_valid else None
        v_lead = est.v_lead if est.lead_valid else math.nan
        mono = self.mono()
        # a tail is taken once the plans have been heard for cacc_return_s; trucks heard
        # naming this truck's predecessor before then were there first (not joiners)
        settled = mono - self._first_heard >= self.cfg.cacc_return_s
        if settled and not self._settled:
            self._settled = True
            f.pred_since = max(f.pred_since, mono)
        changed = f.step(gap, est.v, v_lead, self.heard, mono, settled, est.v_lead_std)
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
        received = (
            sum(x.received for x in self.receivers.values())
            if self.auto
            else (r.received if r is not None else 0)
        )
        if m is not None:
            now, (t_mark, n_mark) = self.wall(), self._rate_mark
            if now - t_mark > 0.2:  # NaN at the first call: no rate yet
                self.plan_rate_hz = (received - n_mark) / (now - t_mark)
            if not now - t_mark <= 0.2:
                self._rate_mark = (now, received)
        rate = self.plan_rate_hz
        senders = max(1, len(self.receivers)) if self.auto else 1
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
        if self.follow is not None:
            ev = self.follow.events
            out["order"] = {
                "standby": self.follow.standby.sender or None,
                "senders": sorted(self.receivers),
                "senders_refused": self.senders_refused,
                "changes": len(ev),
                "last_change": ev[-1][1] if ev else None,
            }
        return out
