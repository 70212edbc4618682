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

Scenarios (all start as a platoon in steady CACC at the lead's speed):

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
import heapq
import math
import random
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from truckd.control.controller import ControlOutput
from truckd.control.estimator import Estimate
from truckd.control.platoon import (
    ACC,
    CACC,
    Plan,
    PlatoonConfig,
    PlatoonDecision,
    PlatoonMode,
    lead_forecast,
    make_plan,
)
from truckd.control.platoon_order import (
    CLOSER,
    FARTHER,
    joiner_for,
    range_jump,
    standby_for,
    tail_candidate,
)
from truckd.control.qp import ControlModel
from truckd.io.port import companion_port
from truckd.runtime.cycle import CompanionCycle, CycleInputs, CycleOutputs
from truckd.runtime.platoon_clock import PlanClock
from truckd.runtime.platoon_link import cycle_plan, follower_inputs
from truckd.sim.closed_loop import SimSetup
from truckd.sim.truck import build_truck

PLATOON_SCENARIOS: tuple[str, ...] = (
    "platoon-brake",
    "platoon-sine",
    "platoon-comm-loss",
    "platoon-join",
    "platoon-leave",
)
MAX_TRUCKS = 100
ACTUATION_DELAY_S = 0.15
"""Dead time (s) between command and actuation in the platoon scenarios' trucks, known to
their controllers (as ``diagnose`` identifies it): a delay is what makes ACC need a
larger headway than CACC (see docs/platoon.md); without it the MPC's ACC is string
stable at these headways already."""
SETTLE_S = 3.0
"""The spacing errors are taken from this time on: every truck starts at the lead's speed
and gap, but its dead time holds the first commands at 0 V, a transient of its own (not
passed down the platoon); every scenario's disturbance starts later."""


@dataclass(frozen=True)
class PlatoonScenario:
    """Lead speed ``lead_v(t)`` (m/s) and acceleration ``lead_a(t)`` (m/s^2); plan loss
    windows ``(t0, t1, p)``: between t0 and t1 (s) each plan is lost with probability p."""

    name: str
    description: str
    duration: float
    v0: float
    lead_v: Callable[[float], float]
    lead_a: Callable[[float], float]
    loss_windows: tuple[tuple[float, float, float], ...] = ()
    input_delay: float = ACTUATION_DELAY_S
    kind: str = ""
    """"join" or "leave": trucks change places at ``event_s``."""
    event_s: float = math.inf


def _brake_v(t: float) -> float:
    return 1.5 - 2.0 * min(max(t - 4.0, 0.0), 0.5)


def _brake_a(t: float) -> float:
    return -2.0 if 4.0 <= t < 4.5 else 0.0


_W = 2.0 * math.pi / 3.0


def _sine_v(t: float) -> float:
    return 1.2 + 0.4 * math.sin(_W * (t - 3.0)) if t >= 3.0 else 1.2


def _sine_a(t: float) -> float:
    return 0.4 * _W * math.cos(_W * (t - 3.0)) if t >= 3.0 else 0.0


def _dip_v(t: float) -> float:
    """1.2 m/s; at 12 s down to 0.8 m/s at 1 m/s^2, at 16 s back up."""
    if t < 12.0:
        return 1.2
    if t < 16.0:
        return max(1.2 - (t - 12.0), 0.8)
    return min(0.8 + (t - 16.0), 1.2)


def _dip_a(t: float) -> float:
    if 12.0 <= t < 12.4:
        return -1.0
    if 16.0 <= t < 16.4:
        return 1.0
    return 0.0


def _steady_v(t: float) -> float:
    return 1.2


def _steady_a(t: float) -> float:
    return 0.0


def make_platoon_scenario(name: str) -> PlatoonScenario:
    """The scenario ``name`` (see the module docstring)."""
    if name == "platoon-brake":
        return PlatoonScenario(
            name, "lead brakes 1.5 -> 0.5 m/s at 2 m/s^2", 12.0, 1.5, _brake_v, _brake_a
        )
    if name == "platoon-sine":
        return PlatoonScenario(
            name, "lead speed 1.2 + 0.4 sin(2 pi (t - 3 s) / 3 s)", 15.0, 1.2, _sine_v, _sine_a
        )
    if name == "platoon-comm-loss":
        return PlatoonScenario(
            name,
            "plans lost for 2 s, then 30 % loss",
            25.0,
            1.2,
            _dip_v,
            _dip_a,
            loss_windows=((5.0, 7.0, 1.0), (7.0, math.inf, 0.3)),
        )
    if name == "platoon-join":
        return PlatoonScenario(
            name,
            "1.2 m/s; a truck in the next lane announces at 4 s and moves in once room is "
            "open; another drives up from behind and joins at the tail",
            20.0,
            1.2,
            _steady_v,
            _steady_a,
            kind="join",
            event_s=4.0,
        )
    if name == "platoon-leave":
        return PlatoonScenario(
            name,
            "1.2 m/s; at 5 s the middle truck leaves, its follower takes the truck ahead",
            15.0,
            1.2,
            _steady_v,
            _steady_a,
            kind="leave",
            event_s=5.0,
        )
    raise ValueError(
        f"unknown platoon scenario {name!r}; expected one of {', '.join(PLATOON_SCENARIOS)}"
    )


@dataclass(frozen=True)
class LinkConfig:
    """A plan link as it is: each message's delay drawn uniformly in ``delay`` (lo, hi) s
    (so it changes during the run, and messages overtake each other when the range is
    wider than the sending period), lost with probability ``loss``; with ``burst`` the
    losses come in runs (a two-state Gilbert-Elliott channel: the same share lost, runs of
    ``burst_len`` messages on average)."""

    delay: tuple[float, float] = (0.02, 0.02)
    loss: float = 0.0
    burst: bool = False
    burst_len: float = 8.0


class PlanChannel:
    """One sender's plan key as one receiver gets it (:class:`LinkConfig`, plus the
    scenario's loss windows ``(t0, t1, p)``): :meth:`receive` gives the plans delivered
    by a time with their delivery times, in delivery order."""

    def __init__(
        self,
        link: LinkConfig,
        windows: tuple[tuple[float, float, float], ...],
        rng: random.Random,
        name: str = "",
    ) -> None:
        self.name = name
        """``sender->receiver``."""
        self.link = link
        self.windows = windows
        self.rng = rng
        self._inflight: list[tuple[float, int, Plan]] = []
        self._bad = False
        self.sent = 0
        self.lost = 0

    def _lost(self, t: float) -> bool:
        link, rng = self.link, self.rng
        for t0, t1, pw in self.windows:
            if t0 <= t < t1 and rng.random() < pw:
                return True
        p = link.loss
        if not link.burst or p <= 0.0 or p >= 1.0:
            return rng.random() < p
        leave_bad = 1.0 / link.burst_len
        enter_bad = p * leave_bad / (1.0 - p)  # stationary share of the bad state: p
        self._bad = rng.random() >= leave_bad if self._bad else rng.random() < enter_bad
        return self._bad

    def send(self, t: float, plan: Plan) -> None:
        """Publish at time t (s, simulated)."""
        self.sent += 1
        if self._lost(t):
            self.lost += 1
            return
        lo, hi = self.link.delay
        delay = lo if hi <= lo else self.rng.uniform(lo, hi)
        heapq.heappush(self._inflight, (t + delay, self.sent, plan))

    def receive(self, t: float) -> list[tuple[float, Plan]]:
        """The plans delivered by time t (s), with their delivery times."""
        q, out = self._inflight, []
        while q and q[0][0] <= t + 1e-12:
            at, _, plan = heapq.heappop(q)
            out.append((at, plan))
        return out


@dataclass
class PlatoonTrace:
    """Per-truck time series (SI): position, speed, gap to the vehicle the truck's range
    sensor sees (NaN: none; a truck in the next lane before it merges: to its
    predecessor), the reference gap at the headway in use, the headway, the mode
    (CACC/ACC, truck 0: LEAD, a truck that left: OUT), the voltage, the lane (0 the
    platoon's)."""

    t: list[float] = field(default_factory=list)
    x: list[list[float]] = field(default_factory=list)
    v: list[list[float]] = field(default_factory=list)
    gap: list[list[float]] = field(default_factory=list)
    gap_ref: list[list[float]] = field(default_factory=list)
    headway: list[list[float]] = field(default_factory=list)
    mode: list[list[str]] = field(default_factory=list)
    u: list[list[float]] = field(default_factory=list)
    accel: list[list[float]] = field(default_factory=list)
    lane: list[list[int]] = field(default_factory=list)
    predecessor: list[list[str]] = field(default_factory=list)
    supervisor: list[list[str]] = field(default_factory=list)
    rows: list[list[tuple[float, ...]]] = field(default_factory=list)
    """Per truck (truck 0, the lead, first): the daemon's log row each cycle with the truth
    appended, as :class:`~truckd.sim.closed_loop.Trace` rows (``--trace``)."""


MIXED_EFFECTS: tuple[tuple[str, float, float], ...] = (
    ("viscous_friction", 0.0, 3e-5),
    ("aero_drag", 0.0, 0.8),
    ("load_force", 0.0, 1.5),
    ("battery_sag", 0.0, 0.05),
    ("dead_zone", 0.0, 0.4),
)
"""``--mixed``: the effects a truck draws one of, and its range (SI, truckd/model/effects.py)."""


def draw_platoon_truck(setup: SimSetup, rng: random.Random) -> SimSetup:
    """A truck of a mixed platoon: mass 0.6-2x the configured (the inertia reflected to the
    motor with it), motor constant 0.8-1.3x (friction torques with it), armature
    resistance 0.8-1.5x, and one effect of :data:`MIXED_EFFECTS` at a drawn magnitude.
    Its controller's model is the drawn truck itself (its true parameters and effects, as
    a perfect ``diagnose`` would give them)."""
    p = setup.plant_params
    m = p.m * rng.uniform(0.6, 2.0)
    k = rng.uniform(0.8, 1.3)
    reflected = p.ratio**2  # (r_w / (n_g n_fd))^2: kg at the wheel -> kg m^2 at the motor
    q = p.replace(
        m=m,
        J_S=max(p.J_S + (m - p.m) * reflected, 0.2 * p.J_S),
        K_v=p.K_v * k,
        K_T=p.K_T * k,
        K_coulomb=p.K_coulomb * k,
        K_stiction=p.K_stiction * k,
        R_m=p.R_m * rng.uniform(0.8, 1.5),
    )
    name, lo, hi = MIXED_EFFECTS[rng.randrange(len(MIXED_EFFECTS))]
    eff = replace(setup.plant_config.effects, **{name: rng.uniform(lo, hi)})
    # Tuned in acceleration, not volts: the rate weight scaled by the square of the
    # acceleration a volt gives (K_T / (R_m J_S)), so every truck responds alike.
    gain = (q.K_T / (q.R_m * q.J_S)) / (p.K_T / (p.R_m * p.J_S))
    return replace(
        setup,
        control=replace(setup.control, r_du=setup.control.r_du * gain**2),
        plant_params=q,
        plant_config=replace(setup.plant_config, effects=eff),
        model=ControlModel(q, eff),
    )


class _Source:
    """A sender's plans as one receiver holds them: the newest (by ``seq``, or a sender
    that restarted) and the sender's clock."""

    def __init__(self, sender: str) -> None:
        self.sender = sender
        self.clock = PlanClock()
        self.held: Plan | None = None

    def take(self, arrivals: list[tuple[float, Plan]], own: Callable[[float], float]) -> None:
        for at, plan in arrivals:
            self.clock.observe(plan, own(at))
            old = self.held
            if old is None or plan.seq > old.seq or plan.t > old.t + 1.0:
                self.held = plan


class _Truck:
    def __init__(
        self,
        vid: str,
        setup: SimSetup,
        pcfg: PlatoonConfig,
        x0: float,
        v0: float,
        range_fn: Any,
        clock: tuple[float, float],
        predecessor: str,
        initial: str = CACC,
    ) -> None:
        self.vid = vid
        cfg = setup.control
        spec = setup.truck
        truck = build_truck(spec, range_fn, v0=v0, x0=x0)
        assert truck.link is not None
        self.plant, self.fw, self.link = truck.plant, truck.firmware, truck.link
        self.port = companion_port(self.link, clock=lambda: self.plant.t)
        self.cyc = CompanionCycle(
            setup.model,
            cfg,
            setup.supervisor,
            spec.firmware.ticks_per_rev,
            setup.stop_ramp_v_per_s,
            time_budget=False,  # simulated time: judged by what the solver did
        )
        self.mode = PlatoonMode(pcfg, cfg.period, self.cyc.controller.forecast_steps, initial)
        self.clock_offset, self.clock_drift = clock
        self.predecessor = predecessor
        self.source = _Source(predecessor)
        self.standby = _Source("")
        self.lane = 0
        self.active = True
        self.announce = True
        """Publishes its plans (a truck about to join in the middle is silent until it
        announces)."""
        self.range_prev: float | None = None
        self.pred_since = 0.0
        """When this truck took its predecessor (simulated time, s)."""
        self.out: CycleOutputs | None = None
        self.dec: PlatoonDecision | None = None
        self.order: Callable[[float | None], bool] | None = None
        """Who to follow, given the gap the lead filter measures this cycle (None: no
        lead); True when the predecessor changed."""
        self._sync = True
        self._now = 0.0
        ctl = self.cyc.controller
        law = ctl.control

        def control(
            est: Estimate, forecast: Sequence[float] | None = None, headway: float | None = None
        ) -> ControlOutput:
            # Between the estimate and the control law: a new vehicle ahead is seen by
            # the order and the controller in the same cycle (no step on a stale headway).
            if self.order is not None and self.order(est.gap if est.lead_valid else None):
                forecast, headway = self._redecide()
            return law(est, forecast, headway)

        setattr(ctl, "control", control)  # noqa: B010 (an instance's own control law)

    def _redecide(self) -> tuple[list[float] | None, float]:
        """After a change of predecessor within the cycle: the new headway and forecast."""
        plan = self.plan_in(self._sync)
        m = self.mode
        fc = None
        if m.mode == CACC and plan is not None and m.fresh(plan, self._now):
            fc = lead_forecast(plan, self._now, m.period, m.horizon)
        if self.dec is not None:
            self.dec = replace(self.dec, headway=m.headway, forecast=fc)
        return fc, m.headway

    def own(self, t: float) -> float:
        """This truck's clock at simulated time t (s)."""
        return self.clock_offset + (1.0 + self.clock_drift) * t

    def plan_in(self, sync: bool) -> Plan | None:
        """The predecessor's newest plan on this truck's clock (as received when the
        clocks are taken as synchronised)."""
        return self.source.clock.to_own(self.source.held) if sync else self.source.held

    def cycle(self, t: float, plan: Plan | None) -> None:
        """One cycle at simulated time t (s): the daemon's companion cycle with the
        platoon's forecast and headway (decided on the truck's own clock); the command
        goes to the simulated firmware."""
        self._now = self.own(t)
        self.dec = follower_inputs(self.mode, self._now, plan, self.out, self.cyc.control_cfg.d_0)
        self.out = self.cyc.step(
            CycleInputs(
                t,
                self.port.poll(),
                self.link.connected,
                lead_forecast=self.dec.forecast,
                headway=self.dec.headway,
            )
        )
        self.port.send(self.out.command)
        if self.out.heartbeat is not None:
            self.port.send(self.out.heartbeat)

    def time_gap(self, gap: float) -> float:
        d_0 = self.cyc.control_cfg.d_0
        return (gap - d_0) / self.plant.v if self.plant.v > 0.1 else math.nan


RANGE_JUMP_M = 0.25
"""A change of the measured gap larger than this within one cycle is another vehicle ahead
(a join or a leave): at 2 m/s^2 of relative braking a gap changes by 0.02 m per 10 ms."""


def _targets(
    trucks: list[_Truck], x_driver: float, range_max: float
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
) -> tuple[dict[str, Any], PlatoonTrace]:
    """Run one platoon scenario; returns the contract metrics and a trace.

    ``delay_s`` a plan's delivery delay (s), or a range each message's delay is drawn in;
    ``loss`` the share of plans lost per link (``burst_loss``: in runs); every truck's clock
    has an offset drawn in +-``clock_offset_s`` and a drift in +-``clock_drift_ppm``;
    ``mixed``: every truck drawn (:func:`draw_platoon_truck`), from ``seed``.

    The controllers' configured headway is the CACC headway (their QP is built for it;
    the ACC headway is driven by the gap shift, see :meth:`Controller.control`).  The
    trucks' dead time is the scenario's ``input_delay`` unless the plant's is larger; the
    controllers' model knows it."""
    low = MIN_TRUCKS.get(sc.kind, 2)
    if not low <= n_trucks <= MAX_TRUCKS:
        raise ValueError(f"{sc.name}: a platoon has {low} to {MAX_TRUCKS} trucks, got {n_trucks}")
    cfg = replace(setup.control, time_headway=pcfg.cacc_headway)
    setup = replace(setup, control=cfg)
    rng = random.Random(seed)
    setups = [draw_platoon_truck(setup, rng) if mixed else setup for _ in range(n_trucks)]
    setups = [_with_delay(s, sc.input_delay) for s in setups]
    lo, hi = (delay_s, delay_s) if isinstance(delay_s, float | int) else delay_s
    link = LinkConfig((float(lo), float(hi)), loss, burst_loss)
    dt = cfg.period
    dur = sc.duration if duration is None else duration
    gap0 = cfg.d_0 + pcfg.cacc_headway * sc.v0
    xv = [gap0]  # the lead's driver: a virtual vehicle on the scenario's profile
    trucks: list[_Truck] = []
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

        pre, x0, initial = (f"truck{i - 1}" if i else DRIVER), -i * gap0, CACC
        if sc.kind == "join" and i == n_trucks - 2:
            pre, x0 = f"truck{room - 1}", -room * gap0
        elif sc.kind == "join" and i == n_trucks - 1:
            pre, x0, initial = "", -(n_line - 1) * gap0 - TAIL_JOIN_BEHIND_M, ACC
        trucks.append(
            _Truck(f"truck{i}", setups[i], pcfg, x0, sc.v0, range_fn, clocks[i], pre, initial)
        )
    if sc.kind == "join":
        trucks[-2].lane, trucks[-2].announce = 1, False
    links: dict[tuple[str, str], PlanChannel] = {}
    heard = _Heard()
    range_max = cfg.estimator.range_max
    seen[:], _ = _targets(trucks, xv[0], range_max)
    steps = trucks[0].cyc.controller.forecast_steps + 1
    tr = PlatoonTrace()
    events: list[tuple[float, str]] = []
    cycles = max(1, round(dur / dt))
    for k in range(cycles):
        t = k * dt
        if sc.kind == "leave" and t >= sc.event_s and trucks[n_trucks // 2].active:
            gone = trucks[n_trucks // 2]
            gone.active, gone.lane = False, 1
            heard.forget(gone.vid)
            events.append((t, f"{gone.vid} leaves"))
        if sc.kind == "join" and t >= sc.event_s and not trucks[-2].announce:
            trucks[-2].announce, trucks[-2].pred_since = True, t
            events.append((t, f"{trucks[-2].vid} announces: joins behind {trucks[-2].predecessor}"))
        seen[:], true_gaps = _targets(trucks, xv[0], range_max)
        if sc.kind == "join" and trucks[-2].lane == 1 and trucks[-2].announce:
            _try_merge(trucks[-2], trucks, cfg.d_0, pcfg, events, t)
            seen[:], true_gaps = _targets(trucks, xv[0], range_max)
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
                f.order = functools.partial(_order, f, heard=heard, pcfg=pcfg, events=events, t=t)
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
        _record(tr, t, sc.lead_v(t), cfg.d_0, trucks, true_gaps)
        xv[0] += 0.5 * (sc.lead_v(t) + sc.lead_v(t + dt)) * dt
        for f in trucks:
            if f.active:
                f.fw.step(dt)
    m = platoon_metrics(sc.name, n_trucks, tr, trucks[1:], list(links.values()), pcfg)
    m["events"] = [{"t_s": round(te, 6), "what": w} for te, w in events]
    m["clock_offset_s"] = [c[0] for c in clocks]
    m["clock_drift_ppm"] = [c[1] * 1e6 for c in clocks]
    if mixed:
        m["trucks_drawn"] = [_drawn(s) for s in setups]
    return m, tr


DRIVER = "driver"
TAIL_JOIN_BEHIND_M = 3.0
"""``platoon-join``: the joining tail truck starts this far behind the tail (within the
range sensor's 4 m), at the platoon's speed, without a predecessor (ACC): it finds the
tail from its range sensor and the plans heard, and closes up."""
MIN_TRUCKS = {"join": 4, "leave": 3}
ACCEL_WINDOW_S = 0.5
"""The acceleration ratios' moving mean (s)."""


def _with_delay(s: SimSetup, delay: float) -> SimSetup:
    pc, model = s.plant_config, s.model
    d = max(pc.effects.input_delay, delay)
    return replace(
        s,
        plant_config=replace(pc, effects=replace(pc.effects, input_delay=d)),
        model=replace(model, effects=replace(model.effects, input_delay=d)),
    )


def _drawn(s: SimSetup) -> dict[str, Any]:
    p, eff = s.plant_params, s.plant_config.effects
    return {
        "m": p.m,
        "K_v": p.K_v,
        "R_m": p.R_m,
        "effects": {n: getattr(eff, n) for n in eff.active()},
    }


class _Heard:
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


def _order(
    f: _Truck,
    gap: float | None,
    *,
    heard: _Heard,
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
            f.predecessor, f.source, f.pred_since = pick, _Source(pick), t
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
        f.standby = _Source(want)
    if joiner and f.mode.extra_headway == 0.0 and f.plant.v > 0.1:
        # room for the joining truck: its own CACC gap (d_0 + h v) as extra headway
        f.mode.extra_headway = (d_0 + pcfg.cacc_headway * f.plant.v) / f.plant.v
        events.append((t, f"{f.vid} opens room for {joiner}"))
    return False


def _swap(
    f: _Truck, gap: float | None, events: list[tuple[float, str]], t: float, why: str
) -> None:
    old = f.predecessor
    f.predecessor, f.source, f.standby = f.standby.sender, f.standby, _Source("")
    f.pred_since = t
    f.mode.extra_headway = 0.0
    if gap is not None:
        f.mode.retarget(f.time_gap(gap))
    events.append((t, f"{f.vid} follows {f.predecessor} ({old} {why})"))


def _try_merge(
    j: _Truck,
    trucks: list[_Truck],
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


def _record(
    tr: PlatoonTrace,
    t: float,
    v_driver: float,
    d_0: float,
    trucks: list[_Truck],
    gaps: list[float],
) -> None:
    tr.t.append(t)
    nan = math.nan
    xs: list[float] = []
    vs: list[float] = []
    refs: list[float] = []
    hs: list[float] = []
    modes: list[str] = []
    us: list[float] = []
    acc: list[float] = []
    lanes: list[int] = []
    pres: list[str] = []
    for i, f in enumerate(trucks):
        live = f.active and f.dec is not None and f.out is not None
        xs.append(f.plant.x if live else nan)
        vs.append(f.plant.v if live else nan)
        refs.append(d_0 + f.dec.headway * f.plant.v if live and f.dec is not None else nan)
        hs.append(f.dec.headway if live and f.dec is not None else nan)
        modes.append(("LEAD" if i == 0 else f.dec.mode) if live and f.dec is not None else "OUT")
        us.append(f.out.command.voltage if live and f.out is not None else nan)
        acc.append(nan)
        lanes.append(f.lane)
        pres.append(f.predecessor)
    tr.x.append(xs)
    tr.v.append(vs)
    tr.gap.append(list(gaps))
    tr.gap_ref.append(refs)
    tr.headway.append(hs)
    tr.mode.append(modes)
    tr.u.append(us)
    tr.accel.append(acc)
    tr.lane.append(lanes)
    tr.predecessor.append(pres)
    tr.supervisor.append(
        [f.out.mode.value if f.active and f.out is not None else "OUT" for f in trucks[1:]]
    )
    if not tr.rows:
        tr.rows = [[] for _ in trucks]
    by_id = {f.vid: f for f in trucks}
    for j, f in enumerate(trucks):
        if not f.active or f.out is None:
            continue
        ahead = by_id.get(f.predecessor)
        v_ahead = v_driver if j == 0 else (ahead.plant.v if ahead is not None else nan)
        tr.rows[j].append(
            (*f.cyc.log_row(f.out), f.plant.v, gaps[j], v_ahead, f.plant.x, f.plant.motor.i)
        )


def string_ratios(err: np.ndarray) -> tuple[list[float], list[float]]:
    """``(l2, max)`` ratios for each follower i >= 2 from spacing errors ``err`` (rows:
    samples; columns: followers 1..N-1)."""
    l2, mx = [], []
    for j in range(1, err.shape[1]):
        a, b = err[:, j - 1], err[:, j]
        l2.append(float(np.linalg.norm(b) / np.linalg.norm(a)) if np.any(a) else math.inf)
        mx.append(float(np.max(np.abs(b)) / np.max(np.abs(a))) if np.any(a) else math.inf)
    return l2, mx


def platoon_metrics(
    name: str,
    n_trucks: int,
    tr: PlatoonTrace,
    followers: list[_Truck],
    channels: list[PlanChannel],
    pcfg: PlatoonConfig,
) -> dict[str, Any]:
    """The contract keys (reference section 1) plus switch times and decelerations.
    Columns are trucks by index (with joins and leaves, the pairs of the ratios are the
    trucks' indices, not their order on the road); collision and minimum gap are over
    the platoon's lane."""
    t = np.asarray(tr.t)
    lane = np.asarray(tr.lane)[:, 1:]
    all_gaps = np.asarray(tr.gap, dtype=float)[:, 1:]
    gaps = np.where(lane == 0, all_gaps, np.nan)
    err = np.nan_to_num(gaps - np.asarray(tr.gap_ref, dtype=float)[:, 1:])
    keep = t >= SETTLE_S if len(t) and t[-1] >= 2.0 * SETTLE_S else np.ones(len(t), dtype=bool)
    l2, mx = string_ratios(err[keep])
    modes = np.asarray(tr.mode)[:, 1:]
    v = np.asarray(tr.v, dtype=float)
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    accel = np.diff(v, axis=0) / dt
    min_gap = float(np.nanmin(gaps))
    first_acc = [
        float(t[np.argmax(modes[:, j] == ACC)]) if np.any(modes[:, j] == ACC) else None
        for j in range(modes.shape[1])
    ]
    live = modes != "OUT"
    # acceleration ratios: the 0.5 s mean of each truck's true acceleration (the lead's
    # manoeuvre as it travels down the platoon; a truck's own actuation ripple, from a
    # dead zone or the encoder, averaged out), pairs as above
    win = max(1, round(ACCEL_WINDOW_S / dt))
    smooth = np.array(
        [
            np.convolve(np.nan_to_num(accel[:, j]), np.ones(win) / win, "same")
            for j in range(1, accel.shape[1])
        ]
    ).T.reshape(len(accel), -1)
    a_l2, a_mx = string_ratios(smooth[keep[1:]])
    return {
        "scenario": name,
        "trucks": n_trucks,
        "collision": bool(min_gap <= 0.0),
        "min_gap_m": min_gap,
        "string_ratio_l2": l2,
        "string_ratio_max": mx,
        "cacc_fraction": [
            float(np.mean(modes[live[:, j], j] == CACC)) for j in range(modes.shape[1])
        ],
        # Extensions:
        "min_gap_per_follower_m": [
            float(np.nanmin(gaps[:, j])) if np.any(np.isfinite(gaps[:, j])) else None
            for j in range(gaps.shape[1])
        ],
        "spacing_error_max_m": [float(np.max(np.abs(err[keep, j]))) for j in range(err.shape[1])],
        "first_acc_s": first_acc,
        "mode_switches": [f.mode.switches for f in followers],
        "min_accel_m_s2": [float(np.nanmin(accel[keep[1:], j])) for j in range(1, accel.shape[1])],
        "accel_ratio_l2": a_l2,
        "accel_ratio_max": a_mx,
        "cacc_headway_s": pcfg.cacc_headway,
        "acc_headway_s": pcfg.acc_headway,
        "plans_sent": sum(c.sent for c in channels),
        "plans_lost": sum(c.lost for c in channels),
        "solver_failures": [f.cyc.controller.solver_failures for f in followers],
        "supervisor_modes": [sorted(set(m)) for m in zip(*tr.supervisor, strict=True)],
        "duration_s": round(float(t[-1] + dt), 6),
    }
