"""``platoon.order: auto`` in the daemon: the truck finds whom to follow from its range
sensor and the plans heard on ``truckd/*/plan`` (the tail ahead, the truck that joins in
front of it, the predecessor's predecessor when the predecessor leaves), decided between
each cycle's estimate and its control law (:class:`DaemonPlatoon`, the order of
:mod:`truckd.runtime.platoon_follow` that ``truckd sim --platoon`` uses too)."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import zenoh
from runtime_support import (
    endpoint,
    follower_config,
    free_port,
    run_daemon_beside,
    wait_for,
    watch_vehicle,
)

from truckd.config.truck import load_config
from truckd.control.estimator import Estimate
from truckd.control.platoon import (
    ACC,
    CACC,
    PlatoonConfig,
    encode_plan,
    kinematic_plan,
    platoon_control,
)
from truckd.control.qp import ControlModel
from truckd.runtime.cycle import CompanionCycle
from truckd.runtime.daemon import Daemon
from truckd.runtime.plan_hearing import HEAR_OTHERS_EVERY, MAX_SENDERS, SILENT_S
from truckd.runtime.platoon_follow import LEAD_GONE_S
from truckd.runtime.platoon_join import join_key
from truckd.runtime.platoon_link import DaemonPlatoon
from truckd.runtime.telemetry import zenoh_config

PERIOD = 0.01


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _daemon_platoon(predecessor: str = "", order: str = "auto") -> tuple[DaemonPlatoon, Clock]:
    cfg = load_config()
    pcfg: PlatoonConfig = replace(cfg.platoon, order=order, predecessor=predecessor)
    cyc = CompanionCycle(
        ControlModel(cfg.vehicle),
        platoon_control(cfg.control, pcfg),
        cfg.runtime.supervisor,
        cfg.ticks_per_rev,
        cfg.runtime.stop_ramp_v_per_s,
        time_budget=False,
    )
    clock = Clock()
    return DaemonPlatoon("me", pcfg, cyc, wall=clock, mono=clock), clock


def _estimate(gap: float | None, v: float, v_lead: float) -> Estimate:
    return Estimate(
        v=v, speed_valid=True, gap=gap if gap is not None else 0.0, v_lead=v_lead,
        lead_valid=gap is not None, lead_status="ok" if gap is not None else "none",
        gap_std=0.002, outliers=0, reinits=0, encoder_samples=1, range_samples=1,
        v_lead_std=0.02,
    )  # fmt: skip


def _drive(
    dp: DaemonPlatoon,
    clock: Clock,
    senders: dict[str, str],
    cycles: int,
    gap: float | None,
    v: float = 1.0,
    v_lead: float = 1.0,
    seq0: int = 0,
    plan_v: float | None = None,
) -> list[tuple[Any, ...] | None]:
    """``cycles`` cycles: each sender (vehicle id -> the truck it follows) publishes a plan
    at ``plan_v`` (default ``v_lead``), then the daemon decides and the controller's hook
    sees the estimate (the lead at ``v_lead``).  Returns what the hook returned each
    cycle."""
    hook = dp.cyc.controller.redecide
    assert hook is not None
    plan_v = v_lead if plan_v is None else plan_v
    out = []
    for k in range(cycles):
        clock.t += PERIOD
        for vid, pre in senders.items():
            plan = replace(
                kinematic_plan(clock.t, seq0 + k, PERIOD, plan_v, 0.0, 40, vid), predecessor=pre
            )
            dp.hearing.on_sample(f"truckd/{vid}/plan", encode_plan(plan))
        dp.decide(None)
        out.append(hook(_estimate(gap, v, v_lead)))
    assert dp.errors == 0, dp.last_error  # no decision failed (and none hidden)
    return out


def test_auto_order_finds_the_tail_ahead_and_drives_cacc_behind_it() -> None:
    """No predecessor configured, a platoon t0 <- t1 <- t2 heard and a vehicle in range at
    t2's speed: the truck takes t2 (the tail: nobody follows it) and drives CACC on its
    plans.  Not at rest (every plan says 0 m/s there), and not when the vehicle in range
    drives 2 m/s faster than any plan heard (not a truck of the fleet): ACC."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon()
    assert "platoon order runs between" in dp.cyc.controller.backend  # said at start-up
    _drive(dp, clock, {"t0": "", "t1": "t0"}, 10, gap=1.2)
    assert dp.predecessor == ""  # t2 not heard yet: listening
    _drive(dp, clock, fleet, 60, gap=1.2, seq0=10)
    assert dp.predecessor == "t2"
    _drive(dp, clock, fleet, 80, gap=1.2, seq0=70)
    assert dp.decision is not None and dp.decision.mode == CACC
    assert dp.decision.forecast is not None
    h = dp.health()
    assert h["predecessor"] == "t2" and h["order"]["senders"] == ["t0", "t1", "t2"]
    assert "t2 (the tail)" in h["order"]["last_change"]

    at_rest, clock2 = _daemon_platoon()
    _drive(at_rest, clock2, fleet, 90, gap=1.2, v=0.0, v_lead=0.0)
    assert at_rest.predecessor == ""  # at rest every plan says 0 m/s: no tail taken
    stranger, clock3 = _daemon_platoon()  # plans at 1.0 m/s, the vehicle in range at 3.0
    _drive(stranger, clock3, fleet, 90, gap=1.2, v_lead=3.0, plan_v=1.0)
    assert stranger.predecessor == ""
    assert stranger.decision is not None and stranger.decision.mode == ACC


def test_auto_order_takes_the_predecessors_predecessor_when_it_leaves() -> None:
    """Behind t2 (configured) in CACC, t1 ahead of it: when the range sensor jumps farther
    (t2 left the lane) the truck follows t1 in the same cycle, on t1's fresh plan (held as
    the standby's all along), without a switch to ACC.  Without the jump it stays."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    assert dp.decision is not None and dp.decision.mode == CACC
    assert dp.health()["order"]["standby"] == "t1"
    switches = dp.mode.switches if dp.mode is not None else -1
    _drive(dp, clock, fleet, 20, gap=1.0, seq0=80)
    assert dp.predecessor == "t2"  # no jump: no change
    got = _drive(dp, clock, fleet, 1, gap=2.3, seq0=100)
    assert dp.predecessor == "t1"
    assert got[0] is not None and got[0][0] is not None  # this cycle: t1's forecast
    _drive(dp, clock, fleet, 30, gap=2.3, seq0=101)
    assert dp.decision is not None and dp.decision.mode == CACC
    assert dp.mode is not None and dp.mode.switches == switches


def test_a_lead_dropout_is_no_leave() -> None:
    """Behind t2 (t1 ahead of it heard): cycles without a lead (a range dropout, the lead
    filter restarting after a stall), shorter than LEAD_GONE_S, then the same gap again:
    the truck still follows t2."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    assert dp.health()["order"]["standby"] == "t1"
    _drive(dp, clock, fleet, 1, gap=None, seq0=80)
    _drive(dp, clock, fleet, 10, gap=1.0, seq0=81)
    _drive(dp, clock, fleet, round(0.9 * LEAD_GONE_S / PERIOD), gap=None, seq0=91)
    _drive(dp, clock, fleet, 10, gap=1.0, seq0=200)
    assert dp.predecessor == "t2" and dp.health()["order"]["changes"] == 0


def test_when_the_truck_ahead_goes_and_none_is_known_ahead_of_it_acc() -> None:
    """Behind t0, the platoon's leader (it follows nobody): the range sensor jumps farther
    (t0 left; a car farther ahead): the truck follows nobody and drives ACC from this
    cycle (no forecast), the headway ramped from the time gap it drives.  Likewise when
    nothing is in range for LEAD_GONE_S."""
    fleet = {"t0": ""}
    dp, clock = _daemon_platoon("t0")
    _drive(dp, clock, fleet, 80, gap=0.7)
    assert dp.decision is not None and dp.decision.mode == CACC
    got = _drive(dp, clock, fleet, 1, gap=2.5, seq0=80)
    assert dp.predecessor == "" and got[0] is not None and got[0][0] is None
    assert dp.mode is not None and dp.mode.mode == ACC and dp.mode.headway > 0.5
    assert dp.decision is not None and dp.decision.mode == ACC  # reported so this cycle
    # t0 drives on (next lane), heard, followed by nobody, at the speed of what is ahead:
    # not taken back as a tail
    _drive(dp, clock, fleet, 120, gap=2.5, seq0=81)
    assert dp.predecessor == ""
    gone, clock2 = _daemon_platoon("t0")
    _drive(gone, clock2, fleet, 80, gap=0.7)
    _drive(gone, clock2, fleet, round(LEAD_GONE_S / PERIOD) + 2, gap=None, seq0=80)
    assert gone.predecessor == "" and gone.mode is not None and gone.mode.mode == ACC
    # never in range since it was taken: its plans alone say nothing of it going
    blind, clock3 = _daemon_platoon("t0")
    _drive(blind, clock3, fleet, 80 + round(2 * LEAD_GONE_S / PERIOD), gap=None)
    assert blind.predecessor == "t0"


def test_a_leave_is_a_leave_while_a_join_is_announced() -> None:
    """Behind t1 (t0 ahead of it), a truck j announcing that it follows t1 (room opened):
    t1 leaves (the range sensor jumps farther): the truck follows t0, not t1 nor the
    joiner.  Behind the leader t0 with j announced: t0 leaves: nobody, ACC."""
    dp, clock = _daemon_platoon("t1")
    _drive(dp, clock, {"t0": "", "t1": "t0"}, 80, gap=1.0)
    _drive(dp, clock, {"t0": "", "t1": "t0", "j": "t1"}, 30, gap=1.0, seq0=80)
    assert dp.mode is not None and dp.mode.extra_headway > 0.0
    _drive(dp, clock, {"t0": "", "t1": "t0", "j": "t1"}, 1, gap=2.5, seq0=110)
    assert dp.predecessor == "t0"
    lead, clock2 = _daemon_platoon("t0")
    _drive(lead, clock2, {"t0": ""}, 80, gap=0.7)
    _drive(lead, clock2, {"t0": "", "j": "t0"}, 30, gap=0.7, seq0=80)
    _drive(lead, clock2, {"t0": "", "j": "t0"}, 1, gap=2.5, seq0=110)
    assert lead.predecessor == "" and lead.mode is not None and lead.mode.mode == ACC


def test_the_first_gap_after_a_dropout_is_no_jump() -> None:
    """Half a second without a lead while the gap closed by 0.4 m: the truck still follows
    t2 (a gap that moved during a dropout is not another vehicle)."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    _drive(dp, clock, fleet, 50, gap=None, seq0=80)
    _drive(dp, clock, fleet, 20, gap=1.4, seq0=130)
    assert dp.predecessor == "t2"


def test_a_joiner_that_goes_silent_lets_the_room_close() -> None:
    """j announces that it follows t2 (room opened), then falls silent: once it is
    forgotten (SILENT_S) the room closes (the extra headway back to 0, by the ramp)."""
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, {"t1": "", "t2": "t1"}, 80, gap=1.0)
    _drive(dp, clock, {"t1": "", "t2": "t1", "j": "t2"}, 30, gap=1.0, seq0=80)
    assert dp.mode is not None and dp.mode.extra_headway > 0.0
    n = round(SILENT_S / PERIOD) + 2 * HEAR_OTHERS_EVERY
    _drive(dp, clock, {"t1": "", "t2": "t1"}, n, gap=1.0, seq0=110)
    assert "j" not in dp.hearing.receivers and "j" not in dp.hearing.heard.pre
    assert dp.mode.extra_headway == 0.0 and dp.predecessor == "t2"


def test_silent_senders_are_forgotten_while_searching_too() -> None:
    """No predecessor, two trucks heard, then silent for SILENT_S: forgotten; a vehicle
    in range afterwards is not taken for either of them."""
    dp, clock = _daemon_platoon()
    _drive(dp, clock, {"a": "", "b": "a"}, 30, gap=None)
    _drive(dp, clock, {}, round(SILENT_S / PERIOD) + 2 * HEAR_OTHERS_EVERY, gap=None, seq0=30)
    assert dp.hearing.receivers == {} and dp.hearing.heard.pre == {}
    _drive(dp, clock, {}, 20, gap=1.0, seq0=1000)
    assert dp.predecessor == ""


def test_auto_order_opens_room_for_a_joining_truck_and_follows_it() -> None:
    """Behind t2: a truck j announces that it follows t2 (it will move in in front of this
    truck): the truck opens room (extra headway, ramped) and listens to j; when the range
    sensor jumps closer (j moved in) it follows j."""
    fleet = {"t1": "", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    assert dp.mode is not None and dp.mode.extra_headway == 0.0
    _drive(dp, clock, {**fleet, "j": "t2"}, 20, gap=1.0, seq0=80)
    assert dp.mode.extra_headway > 0.0
    assert dp.health()["order"]["standby"] == "j"
    assert dp.predecessor == "t2"
    _drive(dp, clock, {**fleet, "j": "t2"}, 1, gap=0.6, seq0=100)
    assert dp.predecessor == "j"
    assert dp.mode.extra_headway == 0.0


def test_the_room_for_a_joiner_is_a_cacc_gap_at_the_speed_driven() -> None:
    """A joiner announced while the platoon drives 1.2 m/s, which then settles at 1.0
    m/s: the extra headway follows the speed (a CACC gap at 1.0 m/s, d_0 + h v), not
    the headway of the moment it was heard (a gap 0.06 m short at 1.0 m/s)."""
    fleet = {"t1": "", "t2": "t1", "j": "t2"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, {"t1": "", "t2": "t1"}, 80, gap=1.0, v=1.2, v_lead=1.2)
    _drive(dp, clock, fleet, 20, gap=1.0, v=1.2, v_lead=1.2, seq0=80)
    assert dp.mode is not None
    d_0, h = dp.cyc.control_cfg.d_0, dp.cfg.cacc_headway
    assert abs(dp.mode.extra_headway - (d_0 + h * 1.2) / 1.2) < 0.01
    _drive(dp, clock, fleet, 600, gap=1.0, v=1.0, v_lead=1.0, seq0=100)
    assert abs(dp.mode.extra_headway * 1.0 - (d_0 + h * 1.0)) < 0.005  # the room, m
    order = dp.health()["order"]
    assert order["changes"] == 1 and "opens room for j" in order["last_change"]  # once


def test_trucks_heard_from_the_start_behind_the_same_predecessor_are_no_joiners() -> None:
    """Two daemons started together behind t1 (this one and x, say beside it in the next
    lane): x's plans name t1 from the first one heard, so x was there first, not a truck
    joining in front; no room is opened.  The control case: the same x heard only after
    a second is a joiner."""
    dp, clock = _daemon_platoon("t1")
    _drive(dp, clock, {"t1": "", "x": "t1"}, 150, gap=1.0)
    assert dp.mode is not None and dp.mode.extra_headway == 0.0
    assert dp.health()["order"]["standby"] is None
    late, clock2 = _daemon_platoon("t1")
    _drive(late, clock2, {"t1": ""}, 100, gap=1.0)
    _drive(late, clock2, {"t1": "", "x": "t1"}, 50, gap=1.0, seq0=100)
    assert late.mode is not None and late.mode.extra_headway > 0.0


def test_hostile_plans_never_stop_the_decision() -> None:
    """A plan with a subnormal step (5e-324 s: a sample index past any float) is refused;
    a receiver that raises makes the decision ACC on the range sensor, counted in health's
    ``errors``, not an exception in the loop."""
    dp, clock = _daemon_platoon("t0")
    _drive(dp, clock, {"t0": ""}, 80, gap=0.7)
    bad = json.loads(encode_plan(kinematic_plan(clock.t, 999, PERIOD, 1.0, 0.0, 40, "t0")))
    bad["dt"] = 5e-324
    dp.hearing.on_sample("truckd/t0/plan", json.dumps(bad).encode())
    r = dp.hearing.receivers["t0"]
    refused = r.refused
    dp.decide(None)
    assert r.refused == refused + 1 and "'dt'" in r.last_error

    def broken(max_bytes: int = 0) -> None:
        raise OverflowError("cannot convert float infinity to integer")

    r.latest = broken  # type: ignore[method-assign]
    d = dp.decide(None)
    assert d is not None and d.forecast is None and dp.health()["errors"] == 1


def test_senders_beyond_the_limit_never_lock_out_the_predecessor() -> None:
    """MAX_SENDERS strangers heard first: the configured predecessor's plans are still
    taken (it is always admitted); strangers silent for SILENT_S are forgotten, making
    room for others."""
    dp, clock = _daemon_platoon("t0")
    plan = kinematic_plan(clock.t, 1, PERIOD, 1.0, 0.0, 40, "x")
    for i in range(MAX_SENDERS):
        dp.hearing.on_sample(f"truckd/x{i}/plan", encode_plan(replace(plan, vehicle_id=f"x{i}")))
    dp.hearing.on_sample("truckd/y/plan", encode_plan(replace(plan, vehicle_id="y")))
    assert "y" not in dp.hearing.receivers and dp.hearing.senders_refused == 1
    _drive(dp, clock, {"t0": ""}, 80, gap=0.7)
    assert "t0" in dp.hearing.receivers and dp.decision is not None and dp.decision.mode == CACC
    _drive(dp, clock, {"t0": ""}, round(SILENT_S / PERIOD) + 2 * HEAR_OTHERS_EVERY, gap=0.7)
    assert set(dp.hearing.receivers) == {"t0"}
    dp.hearing.on_sample("truckd/y/plan", encode_plan(replace(plan, vehicle_id="y")))
    assert "y" in dp.hearing.receivers


def test_many_trucks_heard_from_the_start_are_no_joiners_either() -> None:
    """As above with eight more trucks heard from the start (each decoded in turn): none
    of those naming t1 from their first plan is taken for a joiner."""
    fleet = {"t1": "", "x": "t1", **{f"o{i}": f"o{i - 1}" if i else "" for i in range(8)}}
    dp, clock = _daemon_platoon("t1")
    _drive(dp, clock, fleet, 200, gap=1.0)
    assert dp.mode is not None and dp.mode.extra_headway == 0.0


def test_auto_order_hears_other_trucks_plan_keys_only_and_at_most_max_senders() -> None:
    """Its own plans, other keys and senders beyond :data:`MAX_SENDERS` are not heard (the
    last counted); a plan on one truck's key naming another truck is refused."""
    dp, clock = _daemon_platoon()
    plan = kinematic_plan(clock.t, 1, PERIOD, 1.0, 0.0, 40, "me")
    dp.hearing.on_sample("truckd/me/plan", encode_plan(plan))
    dp.hearing.on_sample("truckd/a/state", b"{}")
    dp.hearing.on_sample("truckd/a/b/plan", b"{}")
    assert dp.hearing.receivers == {}
    for i in range(MAX_SENDERS + 5):
        vid = f"s{i}"
        dp.hearing.on_sample(f"truckd/{vid}/plan", encode_plan(replace(plan, vehicle_id=vid)))
    assert len(dp.hearing.receivers) == MAX_SENDERS and dp.hearing.senders_refused == 5
    dp.hearing.on_sample("truckd/s0/plan", encode_plan(replace(plan, vehicle_id="s1", seq=2)))
    r = dp.hearing.receivers["s0"]
    r.latest()
    assert r.refused == 1 and "expected 's0'" in r.last_error


def test_an_operator_tells_a_truck_to_join_behind_another_or_to_drive_alone() -> None:
    """Behind t2 in CACC: told to join behind t1 (the order arrives on Zenoh's thread),
    the truck follows t1 from the next cycle (its plans announce it: the truck behind t1
    opens room); told to drive alone, it follows nobody and drives ACC, and takes no tail
    although one is in range at the platoon's speed; told to join behind t2, it follows
    t2 again.  Each order is counted and said in the health message."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    assert dp.predecessor == "t2" and dp.decision is not None and dp.decision.mode == CACC
    dp.joins.on_payload(b'{"behind": "t1"}')
    assert dp.predecessor == "t2"  # taken by the loop, not on Zenoh's thread
    _drive(dp, clock, fleet, 1, gap=1.0, seq0=80)
    assert dp.predecessor == "t1"
    order = dp.health()["order"]
    assert order["joins_told"] == 1 and order["last_join"] == "join behind t1"
    assert "follows t1 (told to join behind it)" in order["last_change"]
    # moving in: t2 (still in range) changes lanes, t1 comes into range 1.3 m farther:
    # the truck moved in behind t1, no leave of t1
    _drive(dp, clock, fleet, 20, gap=1.0, seq0=81)
    _drive(dp, clock, fleet, 1, gap=2.3, seq0=101)
    _drive(dp, clock, fleet, 20, gap=2.3, seq0=102)
    assert dp.predecessor == "t1"
    # the truck behind t1 hears this one announce it: a joiner, room opened
    behind, clock2 = _daemon_platoon("t1")
    _drive(behind, clock2, {"t0": "", "t1": "t0"}, 80, gap=1.0)
    _drive(behind, clock2, {"t0": "", "t1": "t0", "me2": dp.predecessor}, 20, gap=1.0, seq0=80)
    assert behind.mode is not None and behind.mode.extra_headway > 0.0

    dp.joins.on_payload(b'{"behind": null}')
    _drive(dp, clock, fleet, 1, gap=1.0, seq0=122)
    assert dp.predecessor == "" and dp.mode is not None and dp.mode.mode == ACC
    _drive(dp, clock, fleet, 200, gap=1.0, seq0=123)  # t2: the tail, in range, at speed
    assert dp.predecessor == "" and dp.health()["order"]["alone"] is True
    dp.joins.on_payload(b'{"behind": "t2"}')
    _drive(dp, clock, fleet, 1, gap=1.0, seq0=323)
    assert dp.predecessor == "t2" and dp.health()["order"]["alone"] is False
    assert dp.health()["order"]["joins_told"] == 3


def test_a_truck_told_to_join_moves_in_through_a_gap_without_a_lead() -> None:
    """Told to join behind t1 while t2 is in range: the lane change leaves nothing in
    range for longer than LEAD_GONE_S, then t1 comes into range: the truck still follows
    t1 (what it drove behind going out of range is no leave of t1).  Once t1 has been in
    range, losing it for LEAD_GONE_S is t1 gone again."""
    fleet = {"t0": "", "t1": "t0", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 80, gap=1.0)
    dp.joins.on_payload(b'{"behind": "t1"}')
    _drive(dp, clock, fleet, 10, gap=1.0, seq0=80)
    _drive(dp, clock, fleet, round(2 * LEAD_GONE_S / PERIOD), gap=None, seq0=90)
    assert dp.predecessor == "t1"
    _drive(dp, clock, fleet, 50, gap=1.5, seq0=300)
    assert dp.predecessor == "t1"
    _drive(dp, clock, fleet, round(LEAD_GONE_S / PERIOD) + 2, gap=None, seq0=350)
    assert dp.predecessor == "t0"  # t1 went: the truck ahead of it


def test_join_orders_that_are_not_orders_change_nothing() -> None:
    """Not JSON, not an object, another key, an id that is no vehicle id, this truck
    itself, an order too long: each refused and counted, the truck still behind t2."""
    fleet = {"t1": "", "t2": "t1"}
    dp, clock = _daemon_platoon("t2")
    _drive(dp, clock, fleet, 50, gap=1.0)
    bad = [
        b"nope", b"\xff\xfe", b'["t1"]', b'{"behind": "t1", "also": 1}', b'{"to": "t1"}',
        b'{"behind": 5}', b'{"behind": "t 1"}', b'{"behind": "me"}',
        b'{"behind": "' + b"a" * 300 + b'"}',
    ]  # fmt: skip
    for payload in bad:
        dp.joins.on_payload(payload)
    _drive(dp, clock, fleet, 10, gap=1.0, seq0=50)
    order = dp.health()["order"]
    assert dp.predecessor == "t2" and order["changes"] == 0
    assert order["joins_refused"] == len(bad) and order["joins_told"] == 0
    assert order["last_join"].startswith("refused: ")


def test_only_the_auto_order_takes_join_orders() -> None:
    """A truck with ``platoon.order: fixed`` does not subscribe to join orders (its
    predecessor is the configuration's); with ``auto`` it subscribes to its own key."""
    keys: dict[str, list[str]] = {"fixed": [], "auto": []}
    for order in ("fixed", "auto"):
        dp, _ = _daemon_platoon("t1", order)
        dp.subscribe(
            lambda key, _cb, o=order: keys[o].append(key),
            subscribe_keyed=lambda key, _cb, o=order: keys[o].append(key),
        )
    assert join_key("me") in keys["auto"] and join_key("me") not in keys["fixed"]


def _fleet(
    session: Any, v_lead: float, stop: threading.Event, each: Callable[[], None] | None = None
) -> None:
    """t0 (leading) and t1 (behind t0) publish a plan at ``v_lead`` (m/s) every 10 ms on
    ``session`` until ``stop``; ``each()`` after every pair of plans."""
    pubs = {v: session.declare_publisher(f"truckd/{v}/plan") for v in ("t0", "t1")}
    seq = 0
    while not stop.is_set():
        for vid, pre in (("t0", ""), ("t1", "t0")):
            p = replace(
                kinematic_plan(time.time(), seq, 0.01, v_lead, 0.0, 40, vid), predecessor=pre
            )
            pubs[vid].put(encode_plan(p))
        if each is not None:
            each()
        seq += 1
        time.sleep(0.01)


def test_daemon_with_auto_order_finds_the_tail_over_zenoh(tmp_path: Path) -> None:
    """``truckd run`` (simulated truck, its lead ahead at 0.7 of the set speed) with
    ``platoon.order: auto`` and no predecessor: two trucks' plans heard on the loopback
    router (t0 leads, t1 follows it, at the lead's speed); the daemon follows t1, reaches
    CACC and publishes plans naming t1; its health lists both senders."""
    port = free_port()
    cfg = load_config(follower_config(tmp_path / "truck.yaml", "f1", {"order": "auto"}, port))
    v_lead = 0.7 * cfg.control.v_set
    s = zenoh.open(zenoh_config(listen=[endpoint(port)]))
    got = watch_vehicle(s, "f1")
    states, plans, health = got["state"], got["plan"], got["health"]
    d = Daemon(cfg, "sim", duration=4.0, env={})
    assert run_daemon_beside(d, s, lambda stop: _fleet(s, v_lead, stop)) == 0
    assert wait_for(lambda: bool(plans), 1.0)
    modes = [m.get("platoon") for m in states]
    assert "CACC" in modes, modes[-20:]
    assert plans[-1]["predecessor"] == "t1"
    entries = [h["platoon"] for h in health if "platoon" in h]
    assert entries and entries[-1]["predecessor"] == "t1"
    assert entries[-1]["order"]["senders"] == ["t0", "t1"]
    assert entries[-1]["plans_accepted"] > 10


def test_a_running_daemon_is_told_to_join_over_zenoh(tmp_path: Path) -> None:
    """``truckd run`` (simulated truck) with ``platoon.order: auto`` behind t1 (t0 ahead
    of it heard): once its plans name t1, an operator's session puts ``{"behind": "t0"}``
    on ``truckd/f1/platoon_join``; the daemon's plans then name t0 and its health counts
    the order."""
    port = free_port()
    cfg = load_config(
        follower_config(tmp_path / "truck.yaml", "f1", {"order": "auto", "predecessor": "t1"}, port)
    )
    v_lead = 0.7 * cfg.control.v_set
    s = zenoh.open(zenoh_config(listen=[endpoint(port)]))
    got = watch_vehicle(s, "f1")
    plans, health = got["plan"], got["health"]
    told: list[float] = []

    def tell_when_t1() -> None:
        if not told and any(p.get("predecessor") == "t1" for p in list(plans)):
            s.put(join_key("f1"), json.dumps({"behind": "t0"}))
            told.append(time.time())

    d = Daemon(cfg, "sim", duration=4.0, env={})
    assert run_daemon_beside(d, s, lambda stop: _fleet(s, v_lead, stop, tell_when_t1)) == 0
    assert told, "the daemon's plans never named t1"
    assert wait_for(lambda: bool(plans), 1.0)
    assert plans[-1]["predecessor"] == "t0"
    entries = [h["platoon"] for h in health if "platoon" in h and "order" in h["platoon"]]
    assert entries and entries[-1]["order"]["joins_told"] == 1
    assert entries[-1]["order"]["last_join"] == "join behind t0"
