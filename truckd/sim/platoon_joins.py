"""Joins and leaves in the simulated platoon: what each range sensor sees, who follows
whom (from the gap each lead filter measures and the plans heard,
:mod:`truckd.control.platoon_order`), and when a joining truck moves in."""

from __future__ import annotations

import math

from truckd.control.platoon import Plan, PlatoonConfig
from truckd.control.platoon_order import (
    CLOSER,
    FARTHER,
    joiner_for,
    range_jump,
    standby_for,
    tail_candidate,
)
from truckd.sim.platoon_truck import PlanSource, PlatoonTruck

RANGE_JUMP_M = 0.25
"""A change of the measured gap larger than this within one cycle is another vehicle ahead
(a join or a leave): at 2 m/s^2 of relative braking a gap changes by 0.02 m per 10 ms."""


def lane_targets(
    trucks: list[PlatoonTruck], x_driver: float, range_max: float
) -> tuple[list[float | None], list[float]]:
    """Per truck: the gap its range sensor sees (None: nothing within ``range_max``; a
    truck in the next lane: the gap to its predecessor) and the true gap to whatever is
    ahead in its lane (NaN: nothing), for the trace."""
    lane0 = sorted(
        ((f.plant.x, j) for j, f in enumerate(trucks) if f.active and f.lane == 0), reverse=True
    )
    true = [math.nan] * len(trucks)
    ahead_x = x_driver
    for x, j in lane0:
        true[j] = ahead_x - x
        ahead_x = x
    by_id = {f.vid: f for f in trucks}
    seen: list[float | None] = [None] * len(trucks)
    for j, f in enumerate(trucks):
        if not f.active:
            continue
        if f.lane != 0:
            p = by_id.get(f.predecessor)
            true[j] = p.plant.x - f.plant.x if p is not None else math.nan
        g = true[j]
        seen[j] = g if math.isfinite(g) and g <= range_max else None
    return seen, true


class HeardPlans:
    """The plans heard on ``truckd/*/plan`` (the discovery view; in the simulation taken
    as each plan is sent): who follows whom, since when, and each truck's planned speed
    now."""

    def __init__(self) -> None:
        self.pre: dict[str, str] = {}
        self.since: dict[str, float] = {}
        self.speed: dict[str, float] = {}

    def note(self, vid: str, plan: Plan, t: float) -> None:
        if self.pre.get(vid) != plan.predecessor or vid not in self.since:
            self.since[vid] = t
        self.pre[vid] = plan.predecessor
        self.speed[vid] = plan.v[0]

    def forget(self, vid: str) -> None:
        for d in (self.pre, self.since, self.speed):
            d.pop(vid, None)


def follow_order(
    f: PlatoonTruck,
    gap: float | None,
    *,
    heard: HeardPlans,
    pcfg: PlatoonConfig,
    events: list[tuple[float, str]],
    t: float,
) -> bool:
    """Who this follower follows, from the gap its lead filter measures this cycle and
    the plans heard (:mod:`truckd.control.platoon_order`); a joining truck ahead: room
    opened.  True when the predecessor changed."""
    jump = range_jump(f.range_prev, gap, RANGE_JUMP_M)
    f.range_prev = gap
    d_0 = f.cyc.control_cfg.d_0
    if f.lane != 0:
        return False
    if not f.predecessor:
        if gap is None:
            return False
        est = f.out.control.estimate if f.out is not None and f.out.control is not None else None
        v_lead = est.v_lead if est is not None and est.lead_valid else math.nan
        pick = tail_candidate(f.vid, heard.pre, heard.speed, v_lead, pcfg.plan_speed_tolerance)
        if pick:
            f.predecessor, f.source, f.pred_since = pick, PlanSource(pick), t
            f.mode.retarget(f.time_gap(gap))
            events.append((t, f"{f.vid} follows {pick} (the tail)"))
            return True
        return False
    joiner = joiner_for(f.vid, f.predecessor, heard.pre, heard.since, f.pred_since)
    if joiner and jump == CLOSER and f.standby.sender == joiner:
        _swap(f, gap, events, t, "joined in front")
        return True
    if jump == FARTHER and f.standby.sender and not joiner:
        _swap(f, gap, events, t, "left")
        return True
    want = standby_for(f.vid, f.predecessor, heard.pre, heard.since, f.pred_since)
    if want != f.standby.sender and f.predecessor in heard.pre:  # gone: keep the standby
        f.standby = PlanSource(want)
    if joiner and f.mode.extra_headway == 0.0 and f.plant.v > 0.1:
        # room for the joining truck: its own CACC gap (d_0 + h v) as extra headway
        f.mode.extra_headway = (d_0 + pcfg.cacc_headway * f.plant.v) / f.plant.v
        events.append((t, f"{f.vid} opens room for {joiner}"))
    return False


def _swap(
    f: PlatoonTruck, gap: float | None, events: list[tuple[float, str]], t: float, why: str
) -> None:
    old = f.predecessor
    f.predecessor, f.source, f.standby = f.standby.sender, f.standby, PlanSource("")
    f.pred_since = t
    f.mode.extra_headway = 0.0
    if gap is not None:
        f.mode.retarget(f.time_gap(gap))
    events.append((t, f"{f.vid} follows {f.predecessor} ({old} {why})"))


def try_merge(
    j: PlatoonTruck,
    trucks: list[PlatoonTruck],
    d_0: float,
    pcfg: PlatoonConfig,
    events: list[tuple[float, str]],
    t: float,
) -> None:
    """The truck in the next lane moves in once the truck behind its spot has opened
    room: its own CACC gap behind it."""
    lane0 = [f for f in trucks if f.active and f.lane == 0]
    ahead = [f for f in lane0 if f.plant.x >= j.plant.x]
    behind = [f for f in lane0 if f.plant.x < j.plant.x]
    if not behind or not ahead or min(ahead, key=lambda f: f.plant.x).vid != j.predecessor:
        return  # the spot is not yet between its predecessor and the truck behind
    b = max(behind, key=lambda f: f.plant.x)
    need = d_0 + pcfg.cacc_headway * b.plant.v
    if j.plant.x - b.plant.x >= MERGE_SHARE * need:
        j.lane = 0
        events.append((t, f"{j.vid} moves in behind {j.predecessor}, in front of {b.vid}"))


MERGE_SHARE = 0.97
"""A joining truck moves in when the gap behind its spot is this share of a CACC gap."""
