"""Who follows whom: the platoon's order from the range sensor and the plans heard.

Pure: no I/O, no clock.  Every plan names the sender's predecessor (its optional
``predecessor`` key), so the plans heard on ``truckd/*/plan`` give the chain as the trucks
see it; a truck's own range sensor says when the vehicle ahead changes (a jump of the
measured gap).  Nothing is a fixed list:

- **Joining at the tail** (no predecessor, a vehicle in range): the predecessor is the
  truck nobody follows (the tail) whose plan's speed is nearest the lead speed the range
  sensor measures (:func:`tail_candidate`).
- **Joining in the middle**: the joining truck announces the truck it will follow (its
  plan's ``predecessor``) before it moves in; the truck already behind that one sees the
  announcement (:func:`joiner_for`), opens room, and when its range sensor jumps closer
  takes the joining truck as its predecessor.
- **Leaving**: when the range sensor jumps farther, the predecessor's own predecessor (from
  its last plan) is the truck ahead now.

A follower keeps a *standby* source, the truck it would follow next (:func:`standby_for`:
an announced joiner, else the predecessor's predecessor), and listens to its plans too, so
a change of predecessor finds a fresh plan and a settled clock estimate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

CLOSER = "closer"
FARTHER = "farther"


def range_jump(previous: float | None, gap: float | None, jump_m: float) -> str | None:
    """``CLOSER`` when the measured gap (m) fell by more than ``jump_m`` in one cycle, or a
    target appeared; ``FARTHER`` when it grew by more, or the target went; else None."""
    if previous is None and gap is None:
        return None
    if previous is None:
        return CLOSER
    if gap is None:
        return FARTHER
    if gap < previous - jump_m:
        return CLOSER
    if gap > previous + jump_m:
        return FARTHER
    return None


def joiner_for(
    own: str,
    predecessor: str,
    heard: Mapping[str, str],
    since: Mapping[str, float] | None = None,
    after: float = -math.inf,
) -> str:
    """A truck (other than ``own``) announcing ``predecessor`` as the truck it follows: it
    joins in front of ``own``; "" when none.  ``heard``: vehicle id -> its predecessor;
    ``since``: vehicle id -> when that predecessor was first heard; only announcements
    heard later than ``after`` (when ``own`` took its predecessor) count, so the truck
    that has just moved in does not take the one it moved in front of for a joiner."""
    if not predecessor:
        return ""
    names = sorted(
        v
        for v, p in heard.items()
        if p == predecessor
        and v not in (own, predecessor, "")
        and (since is None or since.get(v, -math.inf) > after)
    )
    return names[0] if names else ""


def standby_for(
    own: str,
    predecessor: str,
    heard: Mapping[str, str],
    since: Mapping[str, float] | None = None,
    after: float = -math.inf,
) -> str:
    """The truck ``own`` would follow next: an announced joiner (:func:`joiner_for`),
    else its predecessor's predecessor ("" when neither)."""
    j = joiner_for(own, predecessor, heard, since, after)
    if j:
        return j
    nxt = heard.get(predecessor, "") if predecessor else ""
    return nxt if nxt not in (own, predecessor) else ""


def tail_candidate(
    own: str,
    heard: Mapping[str, str],
    speeds: Mapping[str, float],
    v_lead: float,
    tolerance: float,
) -> str:
    """For a truck without predecessor and a vehicle in range: the tail (a truck heard that
    nobody follows, not ``own`` and not behind it: a platoon's leader never takes its own
    tail) whose plan speed now (``speeds``, m/s) is nearest the lead
    speed measured (``v_lead``, m/s) and within ``tolerance``; "" when none fits."""
    followed = set(heard.values())
    best, err = "", math.inf
    for v in sorted(heard):
        if v == own or v in followed or v not in speeds or _behind(own, v, heard):
            continue
        e = abs(speeds[v] - v_lead) if math.isfinite(v_lead) else 0.0
        if e <= tolerance and e < err:
            best, err = v, e
    return best


def _behind(own: str, v: str, heard: Mapping[str, str]) -> bool:
    """Whether ``v`` follows ``own``, directly or down a chain of predecessors heard."""
    for _ in range(len(heard)):
        v = heard.get(v, "")
        if not v:
            return False
        if v == own:
            return True
    return False
