"""Who follows whom, from the range sensor and the plans heard (pure functions)."""

from __future__ import annotations

import math

from truckd.control.platoon_order import (
    CLOSER,
    FARTHER,
    joiner_for,
    range_jump,
    standby_for,
    tail_candidate,
)

CHAIN = {"t0": "", "t1": "t0", "t2": "t1", "t3": "t2"}


def test_range_jumps() -> None:
    assert range_jump(1.0, 1.01, 0.25) is None
    assert range_jump(1.5, 0.75, 0.25) == CLOSER
    assert range_jump(0.75, 1.5, 0.25) == FARTHER
    assert range_jump(None, 2.0, 0.25) == CLOSER
    assert range_jump(2.0, None, 0.25) == FARTHER
    assert range_jump(None, None, 0.25) is None


def test_a_joiner_is_an_announcement_newer_than_the_own_predecessor() -> None:
    heard = {**CHAIN, "j": "t1"}
    since = dict.fromkeys(heard, 0.0) | {"j": 4.0}
    assert joiner_for("t2", "t1", heard, since, after=0.0) == "j"
    # the truck that just moved in (took t1 at 4 s) does not take t2 for a joiner
    assert joiner_for("j", "t1", heard, since, after=4.0) == ""
    assert joiner_for("t3", "t2", heard, since, after=0.0) == ""
    assert joiner_for("t0", "", heard) == ""
    # a truck naming itself as its predecessor joins nothing
    assert joiner_for("t2", "t1", {**CHAIN, "t1": "t1"}, since, after=0.0) == ""


def test_the_standby_is_a_joiner_else_the_predecessors_predecessor() -> None:
    assert standby_for("t3", "t2", CHAIN) == "t1"
    assert standby_for("t1", "t0", CHAIN) == ""  # the lead follows nobody
    assert standby_for("t2", "t1", {**CHAIN, "t1": "t1"}) == ""  # naming itself: nobody
    heard = {**CHAIN, "j": "t1"}
    assert standby_for("t2", "t1", heard) == "j"


def test_the_tail_is_the_truck_nobody_follows_whose_speed_fits() -> None:
    speeds = {"t0": 1.2, "t1": 1.2, "t2": 1.2, "t3": 1.2, "x": 0.2}
    assert tail_candidate("new", CHAIN, speeds, 1.21, 0.7) == "t3"
    assert tail_candidate("new", CHAIN, speeds, 3.0, 0.7) == ""  # not what the sensor sees
    two_tails = {**CHAIN, "x": ""}
    assert tail_candidate("new", two_tails, speeds, 0.3, 0.7) == "x"
    assert tail_candidate("new", two_tails, speeds, 1.2, 0.7) == "t3"
    assert tail_candidate("t3", CHAIN, speeds, math.nan, 0.7) == ""  # never itself


def test_a_leader_never_takes_its_own_tail() -> None:
    """The platoon's leader (t0) seeing a vehicle ahead at the platoon's speed: the truck
    nobody follows (t3) is behind it, down the chain, and is not a tail for it; a truck in
    the middle (t1) never takes a tail behind it either.  Another platoon's tail is."""
    speeds = {"t0": 1.2, "t1": 1.2, "t2": 1.2, "t3": 1.2, "y": 1.2}
    assert tail_candidate("t0", CHAIN, speeds, 1.2, 0.7) == ""
    assert tail_candidate("t1", CHAIN, speeds, 1.2, 0.7) == ""
    assert tail_candidate("t0", {**CHAIN, "y": ""}, speeds, 1.2, 0.7) == "y"
