"""Whom a follower follows while trucks join and leave: the plans heard from every truck,
the plan sources of the predecessor and of the standby, and the order's rules
(:mod:`truckd.control.platoon_order`) applied once a cycle between the estimate and the
control law, so that a new vehicle ahead is seen by the order and the controller in the
same cycle.  Used by ``truckd run`` (``platoon.order: auto``, :mod:`.platoon_link`) and by
``truckd sim --platoon`` alike; pure state, no I/O and no clock (times are passed in)."""

from __future__ import annotations

import math
from collections.abc import Callable

from truckd.control.platoon import CACC, Plan, PlatoonConfig, PlatoonMode, lead_forecast
from truckd.control.platoon_order import (
    CLOSER,
    FARTHER,
    joiner_for,
    range_jump,
    standby_for,
    tail_candidate,
)
from truckd.runtime.platoon_clock import PlanClock

RANGE_JUMP_M = 0.25
"""A change of the measured gap larger than this within one cycle is another vehicle ahead
(a join or a leave): at 2 m/s^2 of relative braking a gap changes by 0.02 m per 10 ms."""


TAIL_MIN_SPEED = 0.2
"""m/s: a tail is taken only while this truck and the vehicle ahead surely move at least
this fast (at rest every truck's plan says 0 m/s and the speed check tells nothing apart;
a lead filter that has just found its target, or a truck starting up, is unsure of the
speed)."""


REJOIN_S = 30.0
"""s: a predecessor that went is no tail candidate for this long."""

ROOM_SPEED_TAU_S = 1.0
"""s: time constant of the speed the room for a joining truck is made for."""

LEAD_GONE_S = 1.0
"""s: no lead in range this long while following: the predecessor went (a jump farther;
longer than the lead filter's restarts after a dropout or a stall)."""


class HeardPlans:
    """The plans heard on ``truckd/*/plan`` (the discovery view): who follows whom, since
    when (s, on the receiver's clock), and each truck's planned speed (m/s) at its plan's
    start."""

    def __init__(self) -> None:
        self.pre: dict[str, str] = {}
        self.since: dict[str, float] = {}
        self.speed: dict[str, float] = {}

    def note(self, vid: str, plan: Plan, t: float) -> None:
        """``plan`` heard from ``vid`` at time t (s)."""
        if self.pre.get(vid) != plan.predecessor or vid not in self.since:
            self.since[vid] = t
        self.pre[vid] = plan.predecessor
        self.speed[vid] = plan.v[0]

    def forget(self, vid: str) -> None:
        """``vid`` is no longer heard (it left, or went silent)."""
        for d in (self.pre, self.since, self.speed):
            d.pop(vid, None)


class PlanSource:
    """A sender's plans as one receiver holds them: the newest (by ``seq``, or a sender
    that restarted) and the sender's clock ("" : no sender)."""

    def __init__(self, sender: str) -> None:
        self.sender = sender
        self.clock = PlanClock()
        self.held: Plan | None = None

    def offer(self, plan: Plan, own_t: float) -> None:
        """``plan`` arrived at ``own_t`` (s, the receiver's clock)."""
        self.clock.observe(plan, own_t)
        old = self.held
        if old is None or plan.seq > old.seq or plan.t > old.t + 1.0:
            self.held = plan

    def hold_latest(self, plan: Plan, now: float) -> None:
        """The daemon's way: ``plan`` the newest its receiver holds (already the newest
        by ``seq``), arrived by ``now`` (s, the receiver's clock; noted once)."""
        self.clock.observe_latest(plan, now)
        self.held = plan

    def take(self, arrivals: list[tuple[float, Plan]], own: Callable[[float], float]) -> None:
        """Plans that arrived at the given times (s), ``own`` mapping them to the
        receiver's clock."""
        for at, plan in arrivals:
            self.offer(plan, own(at))

    def on_own_clock(self, sync: bool = True) -> Plan | None:
        """The newest plan restamped on the receiver's clock (as received without
        ``sync``: the clocks taken as agreeing)."""
        return self.clock.to_own(self.held) if sync else self.held


class Follow:
    """One follower's order: its predecessor and standby sources and what its range sensor
    saw last.  :meth:`step` once a cycle with the gap the lead filter measures."""

    def __init__(
        self,
        vid: str,
        predecessor: str,
        mode: PlatoonMode,
        d_0: float,
        t0: float = 0.0,
        events: list[tuple[float, str]] | None = None,
    ) -> None:
        """``d_0`` (m) the standstill gap; ``t0`` (s) when ``predecessor`` was taken;
        ``events``: the list changes are appended to (a new one when None)."""
        self.vid = vid
        self.predecessor = predecessor
        self.source = PlanSource(predecessor)
        self.standby = PlanSource("")
        self.mode = mode
        self.d_0 = d_0
        self.range_prev: float | None = None
        """The last valid gap (m) the lead filter measured."""
        self._seen_lead = t0
        """When the lead filter last had a lead (s)."""
        self._lead_seen = False
        """A lead was seen since the predecessor was taken (only then can it go)."""
        self._gone: dict[str, float] = {}
        """Predecessors that went (vehicle id -> when, s): not taken as a tail again for
        :data:`REJOIN_S` (a leader that left drives on, heard, followed by nobody)."""
        self.pred_since = t0
        """When this truck took its predecessor (s)."""
        self.events: list[tuple[float, str]] = [] if events is None else events
        """``(t, what)`` of every change (a new predecessor, room opened)."""
        self.alone = False
        """Told to drive alone (:meth:`told`): no tail is searched until told to join."""
        self._room_v = 0.0
        self._room_t = t0
        """The speed (m/s) the room for a joiner is made for, low-passed, and when (s)."""
        self._moving_in = False
        """Told to join: the vehicle in range is still the one driven behind before; the
        first change of it (a jump, or out of range) is the truck moving in, no leave."""

    @property
    def cfg(self) -> PlatoonConfig:
        return self.mode.cfg

    def step(
        self,
        gap: float | None,
        v: float,
        v_lead: float,
        heard: HeardPlans,
        t: float,
        settled: bool = True,
        v_lead_std: float = 0.0,
    ) -> bool:
        """Who this follower follows, from the gap (m; None: no lead) its lead filter
        measures this cycle, its own speed ``v`` and the lead's ``v_lead`` (m/s, NaN:
        unknown) and the plans heard; a joining truck ahead: room opened.  True when the
        predecessor changed (the caller decides the forecast and headway again).
        ``settled``: the plans heard are the whole platoon (a receiver that has listened
        only briefly may not yet have heard the true tail: no change is made before); and
        no tail unless this truck and the vehicle ahead move: ``v`` and the lead's speed
        less three standard deviations ``v_lead_std`` (m/s; NaN: unknown) at least
        :data:`TAIL_MIN_SPEED`."""
        pcfg = self.cfg
        jump = self._jump(gap, t)
        if not self.predecessor:
            if self.alone:
                return False
            moving = v >= TAIL_MIN_SPEED and v_lead - 3.0 * v_lead_std >= TAIL_MIN_SPEED
            if gap is None or not settled or not moving:
                return False
            gone = {vid for vid, when in self._gone.items() if t - when < REJOIN_S}
            view = {vid: p for vid, p in heard.pre.items() if vid not in gone}
            pick = tail_candidate(self.vid, view, heard.speed, v_lead, pcfg.plan_speed_tolerance)
            if pick:
                self._take(PlanSource(pick), gap, v, t, "the tail")
                return True
            return False
        if not settled:
            return False
        joiner = joiner_for(self.vid, self.predecessor, heard.pre, heard.since, self.pred_since)
        if jump == CLOSER and joiner and self.standby.sender == joiner:
            self._take(self.standby, gap, v, t, f"{joiner} joined in front")
            return True
        if jump == FARTHER:  # the predecessor went, whatever was announced meanwhile
            old = self.predecessor
            # the truck ahead of it: from its plans, else (no longer heard) the standby
            # kept as the predecessor's predecessor (not an announced joiner)
            ahead = heard.pre.get(old, "" if joiner else self.standby.sender)
            self._gone[old] = t
            if ahead in ("", self.vid, old):  # no truck known ahead of it: ACC, search
                self._lose(gap, v, t, old)
            else:
                src = self.standby if self.standby.sender == ahead else PlanSource(ahead)
                self._take(src, gap, v, t, f"{old} left")
            return True
        want = standby_for(self.vid, self.predecessor, heard.pre, heard.since, self.pred_since)
        if want != self.standby.sender and self.predecessor in heard.pre:  # gone: keep it
            self.standby = PlanSource(want)
        if joiner and v > 0.1:
            # room for the joining truck: its own CACC gap (d_0 + h v) as extra headway, at
            # the speed driven while it is announced (low-passed: a room made for the speed
            # of the moment it was heard is too short once the platoon drives faster)
            if self.mode.extra_headway == 0.0:
                self._room_v = v
                self.events.append((t, f"{self.vid} opens room for {joiner}"))
            else:
                self._room_v += min(1.0, (t - self._room_t) / ROOM_SPEED_TAU_S) * (v - self._room_v)
            self._room_t = t
            self.mode.extra_headway = (self.d_0 + pcfg.cacc_headway * self._room_v) / self._room_v
        elif not joiner and self.mode.extra_headway != 0.0:
            # the joiner no longer announced (gone silent, or changed its mind): the room
            # closes by the headway ramp
            self.mode.extra_headway = 0.0
            self.events.append((t, f"{self.vid} closes the room: no truck joins"))
        return False

    def told(self, behind: str | None, gap: float | None, v: float, t: float) -> bool:
        """An operator's order at time t (s): drive behind the truck ``behind`` (it is
        announced in this truck's plans from now: the truck behind it opens room), or
        alone (None: follow nobody, ACC on the range sensor, no tail searched) until told
        otherwise; ``gap`` (m; None: no lead) and ``v`` (m/s) as :meth:`step` has them.
        After an order to join, the first change of the vehicle in range (a jump, or none
        in range) is the truck moving in behind its new predecessor, not a join or a
        leave.  True when the predecessor changed.  This truck itself is refused
        (ValueError)."""
        if behind == self.vid:
            raise ValueError(f"{self.vid} cannot drive behind itself")
        if behind is None:
            self.alone = True
            if not self.predecessor:
                return False
            old = self.predecessor
            self._lose(gap, v, t, old)
            self.events[-1] = (t, f"{self.vid} follows nobody (told to drive alone, left {old})")
            return True
        self.alone = False
        if behind == self.predecessor:
            return False
        self._take(PlanSource(behind), gap, v, t, "told to join behind it")
        self._moving_in, self._lead_seen = gap is not None, False
        return True

    def _jump(self, gap: float | None, t: float) -> str | None:
        """A jump of the range sensor this cycle (CLOSER, FARTHER, None): a valid gap
        against the valid one the cycle before (after cycles without a lead, a dropout
        or the lead filter restarting after a stall, the first gap back is no jump: the
        gap moved meanwhile); no lead for :data:`LEAD_GONE_S` after one was seen behind
        this predecessor is the predecessor gone (FARTHER)."""
        jump = None
        if gap is not None:
            if self.range_prev is not None:
                jump = range_jump(self.range_prev, gap, RANGE_JUMP_M)
            self.range_prev, self._seen_lead = gap, t
            if self._moving_in:  # still behind what it drove behind before the order
                if jump is None:
                    return None
                self._moving_in, jump = False, None  # moved in behind its predecessor
            self._lead_seen = True
        else:
            self.range_prev = None
            self._moving_in = False  # the next lead in range is the new predecessor
            if self.predecessor and self._lead_seen and t - self._seen_lead >= LEAD_GONE_S:
                jump = FARTHER
        return jump

    def _take(self, src: PlanSource, gap: float | None, v: float, t: float, why: str) -> None:
        """Follow ``src``'s sender from now (``why``: for the events)."""
        self.predecessor, self.source, self.standby = src.sender, src, PlanSource("")
        self.pred_since, self._lead_seen, self._moving_in = t, gap is not None, False
        self.mode.extra_headway = 0.0
        if gap is not None:
            self.mode.retarget(self.time_gap(gap, v))
        self.events.append((t, f"{self.vid} follows {src.sender} ({why})"))

    def _lose(self, gap: float | None, v: float, t: float, old: str) -> None:
        """Follow nobody from now: ACC, the headway ramped from the time gap driven."""
        self.predecessor, self.source, self.standby = "", PlanSource(""), PlanSource("")
        self.pred_since, self._lead_seen, self._moving_in = t, False, False
        self.mode.extra_headway = 0.0
        self.mode.fall_back(gap if gap is not None else math.nan, v, self.d_0)
        self.events.append((t, f"{self.vid} follows nobody ({old} went, no truck ahead of it)"))

    def redecide(self, sync: bool, now: float) -> tuple[list[float] | None, float]:
        """After a change of predecessor within a cycle: the headway (s) and the forecast
        (m/s; None unless in CACC on a fresh or held plan of the new predecessor) at
        ``now`` (s, this truck's clock)."""
        plan = self.source.on_own_clock(sync)
        m = self.mode
        fc = None
        if m.mode == CACC and plan is not None and (m.fresh(plan, now) or m.held(plan, now)):
            fc = lead_forecast(plan, now, m.period, m.horizon)
        return fc, m.headway

    def time_gap(self, gap: float, v: float) -> float:
        """The time gap (s) driven at gap (m) and speed v (m/s); NaN near standstill."""
        return (gap - self.d_0) / v if v > 0.1 else math.nan
