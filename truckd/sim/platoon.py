"""``truckd sim --platoon N``: N trucks in simulated time, truck 0 leads.

Every truck, the lead (truck 0) included, is a full simulated truck (plant + simulated
firmware + the real protocol on an in-process link)
driven by the daemon's own companion cycle (:class:`~truckd.runtime.cycle.CompanionCycle`:
sensors, controller, supervisor, motor command) with the platoon's part around it
(:func:`follower_inputs`: the CACC/ACC decision, forecast and headway from the latest
plan received; :func:`cycle_plan`: the plan to publish); its range sensor sees the truck
ahead.  The lead's driver is the scenario's speed profile: a virtual vehicle ahead of
truck 0 on that profile, whose plan is the profile itself (a driver who knows what they
will do), so the lead runs the same MPC as every follower and publishes its own MPC plan,
the same plan message as every follower's.  Plans pass through a
:class:`PlanChannel` as they would over Zenoh: a delay, random loss (seeded) and loss
windows.

Scenarios (all start as a platoon in CACC at the lead's speed and the CACC gap; with
``steady_start`` after an unrecorded pre-roll, :data:`PREROLL_S`, that brings every
truck's controller, supervisor, estimator, dead time and motor current to the steady
state of that speed):

===================== =====================================================================
``platoon-brake``      the lead brakes at 2 m/s^2 from 1.5 to 0.5 m/s and drives on
``platoon-sine``       from 3 s the lead's speed oscillates: 1.2 + 0.4 sin(2 pi t / 3 s) m/s
``platoon-comm-loss``  steady at 1.2 m/s with a lead speed dip; every plan is lost for
                       2 s, then 30 % of the plans are lost: ACC, then CACC again
===================== =====================================================================

Every truck has a dead time of :data:`ACTUATION_DELAY_S` between command and actuation
(known to its controller).

Metrics (reference section 1): the spacing error ``e_i = gap_i - (d_0 + h_i v_i)``
with the true gap and speed and the headway ``h_i`` the follower drives at that time;
for each follower i >= 2 the ratios ``||e_i||_2 / ||e_(i-1)||_2`` and ``max|e_i| /
max|e_(i-1)|`` (string stability when both are <= 1).
"""

from __future__ import annotations

import functools
import random
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from truckd.control.platoon import ACC, CACC, PlatoonConfig, follower_control, make_plan
from truckd.runtime.platoon_follow import HeardPlans
from truckd.runtime.platoon_link import cycle_plan
from truckd.sim.closed_loop import SimSetup
from truckd.sim.plan_channel import LinkConfig, PlanChannel
from truckd.sim.platoon_joins import follow_order, lane_targets, try_merge
from truckd.sim.platoon_metrics import PlatoonTrace, platoon_metrics, record_cycle, string_ratios
from truckd.sim.platoon_scenarios import (
    ACTUATION_DELAY_S,
    PLATOON_SCENARIOS,
    PREROLL_HOLD_S,
    PREROLL_S,
    SETTLE_S,
    PlatoonScenario,
    make_platoon_scenario,
)
from truckd.sim.platoon_truck import PlatoonTruck, draw_platoon_truck, drawn_summary, with_delay

__all__ = [
    "ACTUATION_DELAY_S",
    "MAX_TRUCKS",
    "MIN_TRUCKS",
    "PLATOON_SCENARIOS",
    "PREROLL_S",
    "SETTLE_S",
    "LinkConfig",
    "PlanChannel",
    "PlatoonScenario",
    "PlatoonTrace",
    "draw_platoon_truck",
    "make_platoon_scenario",
    "run_platoon",
    "string_ratios",
]

MAX_TRUCKS = 100
DRIVER = "driver"
TAIL_JOIN_BEHIND_M = 3.0
"""``platoon-join``: the joining tail truck starts this far behind the tail (within the
range sensor's 4 m), at the platoon's speed, without a predecessor (ACC): it finds the
tail from its range sensor and the plans heard, and closes up."""
MIN_TRUCKS = {"join": 4, "leave": 3}

Controllers = Callable[[SimSetup, Sequence[SimSetup]], list[tuple[SimSetup, dict[str, Any]]]]
"""``run_platoon``'s ``controllers``: given the configured truck and the trucks as drawn
(their dead time set), each truck with its controller replaced (the plant kept) and what
that controller's model is, for the JSON (``truckd sim --platoon --mixed``: the model each
truck's own identification drive diagnoses, :mod:`truckd.cli.platoon_diagnosis`)."""


def run_platoon(
    sc: PlatoonScenario,
    setup: SimSetup,
    pcfg: PlatoonConfig,
    n_trucks: int,
    *,
    delay_s: float | tuple[float, float] = 0.02,
    loss: float = 0.0,
    burst_loss: bool = False,
    seed: int = 0,
    duration: float | None = None,
    clock_offset_s: float = 0.0,
    clock_drift_ppm: float = 0.0,
    mixed: bool = False,
    steady_start: bool = False,
    controllers: Controllers | None = None,
) -> tuple[dict[str, Any], PlatoonTrace]:
    """Run one platoon scenario; returns the contract metrics and a trace.

    ``delay_s`` a plan's delivery delay (s), or a range each message's delay is drawn in;
    ``loss`` the share of plans lost per link (``burst_loss``: in runs); every truck's clock
    has an offset drawn in +-``clock_offset_s`` and a drift in +-``clock_drift_ppm``;
    ``mixed``: every truck drawn (:func:`draw_platoon_truck`), from ``seed``;
    ``steady_start``: a scenario that starts at speed starts in the steady state of that
    speed, after the unrecorded pre-roll :data:`PREROLL_S` (not ``platoon-join``); without
    it every truck starts with its controller off at speed; ``controllers``: every truck's
    controller replaced before the run (:data:`Controllers`; the JSON's
    ``trucks_diagnosed``), else a drawn truck's controller has its true parameters.

    The controllers' configured headway is the CACC headway (their QP is built for it;
    the ACC headway is driven by the gap shift, see :meth:`Controller.control`), their
    relative-speed weight the platoon's (:func:`follower_control`, every truck's, the
    lead's included: it follows the scenario's virtual vehicle).  The
    trucks' dead time is the scenario's ``input_delay`` unless the plant's is larger; the
    controllers' model knows it.

    Long because the simulated-time loop steps every truck, plan channel, join and leave
    in the one order the metrics assume; its pieces live in the ``platoon_*`` modules."""
    low = MIN_TRUCKS.get(sc.kind, 2)
    if not low <= n_trucks <= MAX_TRUCKS:
        raise ValueError(f"{sc.name}: a platoon has {low} to {MAX_TRUCKS} trucks, got {n_trucks}")
    cfg = follower_control(setup.control, pcfg)
    setup = replace(setup, control=cfg)
    rng = random.Random(seed)
    setups = [draw_platoon_truck(setup, rng) if mixed else setup for _ in range(n_trucks)]
    setups = [with_delay(s, sc.input_delay) for s in setups]
    diagnosed: list[dict[str, Any]] | None = None
    if controllers is not None:
        pairs = controllers(setup, setups)
        setups, diagnosed = [s for s, _ in pairs], [d for _, d in pairs]
    lo, hi = (delay_s, delay_s) if isinstance(delay_s, float | int) else delay_s
    link = LinkConfig((float(lo), float(hi)), loss, burst_loss)
    dt = cfg.period
    dur = sc.duration if duration is None else duration
    gap0 = cfg.d_0 + pcfg.cacc_headway * sc.v0
    # a start at speed: the pre-roll (PREROLL_S) before 0 s, the first PREROLL_HOLD_S of
    # it with every truck held at the starting speed; not for a join (its joining trucks'
    # approach from the start is the scenario)
    pre = round(PREROLL_S / dt) if steady_start and sc.v0 > 0.0 and sc.kind != "join" else 0
    hold = min(round(PREROLL_HOLD_S / dt), pre)
    t0 = -pre * dt
    back = sc.v0 * t0  # where everyone is at t0, relative to the places at 0 s
    xv = [gap0 + back]  # the lead's driver: a virtual vehicle on the scenario's profile
    trucks: list[PlatoonTruck] = []
    events: list[tuple[float, str]] = []
    clocks = [
        (
            rng.uniform(-clock_offset_s, clock_offset_s),
            rng.uniform(-1.0, 1.0) * clock_drift_ppm * 1e-6,
        )
        for _ in range(n_trucks)
    ]
    seen: list[float | None] = []
    # the platoon at the start: trucks 0..n_line-1 in line; join: one in the next lane
    # beside truck `room` (it follows truck `room - 1`), one far behind the tail
    n_line = n_trucks - 2 if sc.kind == "join" else n_trucks
    room = max(1, n_line // 2)
    for i in range(n_trucks):

        def range_fn(t: float, ego_x: float, i: int = i) -> float | None:
            return seen[i] if i < len(seen) else None

        ahead, x0, initial = (f"truck{i - 1}" if i else DRIVER), -i * gap0, CACC
        if sc.kind == "join" and i == n_trucks - 2:
            ahead, x0 = f"truck{room - 1}", -room * gap0
        elif sc.kind == "join" and i == n_trucks - 1:
            ahead, x0, initial = "", -(n_line - 1) * gap0 - TAIL_JOIN_BEHIND_M, ACC
        trucks.append(
            PlatoonTruck(
                f"truck{i}", setups[i], pcfg, x0 + back, sc.v0, range_fn, clocks[i], ahead,
                initial, t0, events,
            )
        )  # fmt: skip
    starts = [f.plant.x for f in trucks]
    if sc.kind == "join":
        trucks[-2].lane, trucks[-2].announce = 1, False
    links: dict[tuple[str, str], PlanChannel] = {}
    heard = HeardPlans()
    range_max = cfg.estimator.range_max
    seen[:], _ = lane_targets(trucks, xv[0], range_max)
    steps = trucks[0].cyc.controller.forecast_steps + 1
    tr = PlatoonTrace()
    cycles = max(1, round(dur / dt))
    for k in range(-pre, cycles):
        t = k * dt
        if k == 0 and pre:  # the pre-roll is not measured
            for channel in links.values():
                channel.sent = channel.lost = 0
            for f in trucks:
                f.mode.switches = f.cyc.controller.solver_failures = 0
            events.clear()
        if sc.kind == "leave" and t >= sc.event_s and trucks[n_trucks // 2].active:
            gone = trucks[n_trucks // 2]
            gone.active, gone.lane = False, 1
            heard.forget(gone.vid)
            events.append((t, f"{gone.vid} leaves"))
        if sc.kind == "join" and t >= sc.event_s and not trucks[-2].announce:
            trucks[-2].announce, trucks[-2].follow.pred_since = True, t
            events.append((t, f"{trucks[-2].vid} announces: joins behind {trucks[-2].predecessor}"))
        seen[:], true_gaps = lane_targets(trucks, xv[0], range_max)
        if sc.kind == "join" and trucks[-2].lane == 1 and trucks[-2].announce:
            try_merge(trucks[-2], trucks, cfg.d_0, pcfg, events, t)
            seen[:], true_gaps = lane_targets(trucks, xv[0], range_max)
        for i, f in enumerate(trucks):
            if not f.active:
                continue
            if i == 0:
                own = f.own(t)
                driver = make_plan(
                    own, k, dt, [sc.lead_v(t + j * dt) for j in range(steps)], DRIVER
                )
                f.cycle(t, driver)
            else:
                f._sync = pcfg.clock_sync
                f.order = functools.partial(follow_order, f, heard=heard, t=t)
                for src in (f.source, f.standby):
                    if src.sender:
                        ch = links.get((src.sender, f.vid))
                        if ch is not None:
                            src.take(ch.receive(t), f.own)
                f.cycle(t, f.plan_in(pcfg.clock_sync))
            assert f.out is not None
            plan = cycle_plan(f.cyc, f.out, f.own(t), f.vid)
            if plan is None or not f.announce:
                continue
            plan = replace(plan, predecessor="" if i == 0 else f.predecessor)
            heard.note(f.vid, plan, t)
            for g in trucks:
                if g.active and f.vid in (g.source.sender, g.standby.sender):
                    ch = links.get((f.vid, g.vid))
                    if ch is None:
                        ch = links[f.vid, g.vid] = PlanChannel(
                            link, sc.loss_windows, rng, f"{f.vid}->{g.vid}"
                        )
                    ch.send(t, plan)
        if k >= 0:
            record_cycle(tr, t, sc.lead_v(t), cfg.d_0, trucks, true_gaps)
        xv[0] += 0.5 * (sc.lead_v(t) + sc.lead_v(t + dt)) * dt
        for f, x in zip(trucks, starts, strict=True):
            if f.active:
                f.fw.step(dt)
                if k < hold - pre:
                    f.plant.hold(sc.v0, x + sc.v0 * (f.plant.t - t0))
    m = platoon_metrics(sc.name, n_trucks, tr, trucks[1:], list(links.values()), pcfg)
    m["events"] = [{"t_s": round(te, 6), "what": w} for te, w in events]
    m["clock_offset_s"] = [c[0] for c in clocks]
    m["clock_drift_ppm"] = [c[1] * 1e6 for c in clocks]
    m["preroll_s"] = pre * dt  # 0: the trucks started as the scenario has them at 0 s
    if mixed:
        m["trucks_drawn"] = [drawn_summary(s) for s in setups]
    if diagnosed is not None:
        m["trucks_diagnosed"] = diagnosed
    return m, tr
