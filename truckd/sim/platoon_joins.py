"""Joins and leaves in the simulated platoon: what each range sensor sees, who follows
whom (from the gap each lead filter measures and the plans heard,
:mod:`truckd.control.platoon_order`), and when a joining truck moves in."""

from __future__ import annotations

import math

from truckd.control.estimator import Estimate
from truckd.control.platoon import PlatoonConfig
from truckd.runtime.platoon_follow import HeardPlans
from truckd.sim.platoon_truck import PlatoonTruck


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


def follow_order(f: PlatoonTruck, est: Estimate, *, heard: HeardPlans, t: float) -> bool:
    """Who this follower follows, from this cycle's estimate and the plans heard (the
    daemon's order, :class:`~truckd.runtime.platoon_follow.Follow`); a truck in the next
    lane follows the truck it announced until it moves in.  True when the predecessor
    changed."""
    gap = est.gap if est.lead_valid else None
    if f.lane != 0:
        f.follow.range_prev = gap
        return False
    v_lead = est.v_lead if est.lead_valid else math.nan
    return f.follow.step(gap, est.v, v_lead, heard, t, v_lead_std=est.v_lead_std)


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
