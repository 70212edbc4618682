"""``truckd sim --platoon N``: N trucks in simulated time, truck 0 leads.

The lead (truck 0) drives the scenario's speed profile (its driver) and publishes a
constant-acceleration plan from its speed and acceleration.  Every follower is a full
simulated truck (plant + simulated firmware + the real protocol on an in-process link)
driven by the daemon's own companion cycle (:class:`~truckd.runtime.cycle.CompanionCycle`:
sensors, controller, supervisor, motor command) with the platoon's part around it
(:func:`follower_inputs`: the CACC/ACC decision, forecast and headway from the latest
plan received; :func:`cycle_plan`: the plan to publish); its range sensor sees the truck
ahead.  Plans pass through a
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

import math
import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from truckd.control.platoon import (
    ACC,
    CACC,
    Plan,
    PlatoonConfig,
    PlatoonDecision,
    PlatoonMode,
    kinematic_plan,
)
from truckd.io.port import companion_port
from truckd.model.plant_config import encoder_ticks_per_rev
from truckd.runtime.cycle import CompanionCycle, CycleInputs, CycleOutputs
from truckd.runtime.platoon_link import cycle_plan, follower_inputs
from truckd.sim.closed_loop import SimSetup
from truckd.sim.firmware import FirmwareSimConfig, simulated_truck
from truckd.sim.plant import Plant

PLATOON_SCENARIOS: tuple[str, ...] = ("platoon-brake", "platoon-sine", "platoon-comm-loss")
MAX_TRUCKS = 10
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
    raise ValueError(
        f"unknown platoon scenario {name!r}; expected one of {', '.join(PLATOON_SCENARIOS)}"
    )


class PlanChannel:
    """One truck's plan key as seen by its follower: each plan is delivered ``delay_s``
    after it was sent unless lost (probability ``loss``, or a loss window's); the receiver
    holds the newest plan delivered so far."""

    def __init__(
        self,
        delay_s: float,
        loss: float,
        windows: tuple[tuple[float, float, float], ...],
        rng: random.Random,
    ) -> None:
        self.delay_s = delay_s
        self.loss = loss
        self.windows = windows
        self.rng = rng
        self._inflight: deque[tuple[float, Plan]] = deque()
        self.latest: Plan | None = None
        self.sent = 0
        self.lost = 0

    def _loss_at(self, t: float) -> float:
        p = self.loss
        for t0, t1, pw in self.windows:
            if t0 <= t < t1:
                p = max(p, pw)
        return p

    def send(self, t: float, plan: Plan) -> None:
        """Publish at time t (s)."""
        self.sent += 1
        if self.rng.random() < self._loss_at(t):
            self.lost += 1
            return
        self._inflight.append((t + self.delay_s, plan))

    def receive(self, t: float) -> Plan | None:
        """The newest plan delivered by time t (s)."""
        q = self._inflight
        while q and q[0][0] <= t + 1e-12:
            _, plan = q.popleft()
            if self.latest is None or plan.seq > self.latest.seq:
                self.latest = plan
        return self.latest


@dataclass
class PlatoonTrace:
    """Per-truck time series (SI): position, speed, true gap to the truck ahead, the
    reference gap at the headway in use, the headway, the mode (CACC/ACC, lead: LEAD),
    the voltage."""

    t: list[float] = field(default_factory=list)
    x: list[list[float]] = field(default_factory=list)
    v: list[list[float]] = field(default_factory=list)
    gap: list[list[float]] = field(default_factory=list)
    gap_ref: list[list[float]] = field(default_factory=list)
    headway: list[list[float]] = field(default_factory=list)
    mode: list[list[str]] = field(default_factory=list)
    u: list[list[float]] = field(default_factory=list)
    accel: list[list[float]] = field(default_factory=list)
    supervisor: list[list[str]] = field(default_factory=list)
    rows: list[list[tuple[float, ...]]] = field(default_factory=list)
    """Per follower (truck 1 first): the daemon's log row each cycle with the truth
    appended, as :class:`~truckd.sim.closed_loop.Trace` rows (``--trace``)."""


class _Follower:
    def __init__(
        self, setup: SimSetup, pcfg: PlatoonConfig, x0: float, v0: float, range_fn: Any
    ) -> None:
        cfg = setup.control
        ticks = encoder_ticks_per_rev(setup.plant_config.encoder_ticks_per_rev, setup.ticks_per_rev)
        fw_cfg = setup.firmware or FirmwareSimConfig(
            ticks_per_rev=ticks, range_max=cfg.estimator.range_max
        )
        self.plant = Plant(setup.plant_params, setup.plant_config)
        self.plant.reset(v=v0)
        self.plant.x = x0
        self.link, self.fw, _ = simulated_truck(self.plant, range_fn, mode="frames", config=fw_cfg)
        self.port = companion_port(self.link, clock=lambda: self.plant.t)
        self.cyc = CompanionCycle(
            setup.model,
            cfg,
            setup.supervisor,
            fw_cfg.ticks_per_rev,
            setup.stop_ramp_v_per_s,
            time_budget=False,  # simulated time: judged by what the solver did
        )
        self.mode = PlatoonMode(pcfg, cfg.period, self.cyc.controller.forecast_steps, initial=CACC)
        self.out: CycleOutputs | None = None
        self.dec: PlatoonDecision | None = None

    def cycle(self, t: float, plan: Plan | None) -> None:
        """One cycle at simulated time t (s): the daemon's companion cycle with the
        platoon's forecast and headway; the command goes to the simulated firmware."""
        self.dec = follower_inputs(self.mode, t, plan, self.out, self.cyc.control_cfg.d_0)
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


def run_platoon(
    sc: PlatoonScenario,
    setup: SimSetup,
    pcfg: PlatoonConfig,
    n_trucks: int,
    *,
    delay_s: float = 0.02,
    loss: float = 0.0,
    seed: int = 0,
    duration: float | None = None,
) -> tuple[dict[str, Any], PlatoonTrace]:
    """Run one platoon scenario; returns the contract metrics and a trace.

    The controllers' configured headway is the CACC headway (their QP is built for it;
    the ACC headway is driven by the gap shift, see :meth:`Controller.control`).  The
    trucks' dead time is the scenario's ``input_delay`` unless the plant's is larger; the
    controllers' model knows it."""
    if not 2 <= n_trucks <= MAX_TRUCKS:
        raise ValueError(f"a platoon has 2 to {MAX_TRUCKS} trucks, got {n_trucks}")
    cfg = replace(setup.control, time_headway=pcfg.cacc_headway)
    pc, model = setup.plant_config, setup.model
    delay = max(pc.effects.input_delay, sc.input_delay)
    setup = replace(
        setup,
        control=cfg,
        plant_config=replace(pc, effects=replace(pc.effects, input_delay=delay)),
        model=replace(model, effects=replace(model.effects, input_delay=delay)),
    )
    dt = cfg.period
    n = cfg.horizon
    dur = sc.duration if duration is None else duration
    rng = random.Random(seed)
    channels = [PlanChannel(delay_s, loss, sc.loss_windows, rng) for _ in range(n_trucks - 1)]
    gap0 = cfg.d_0 + pcfg.cacc_headway * sc.v0
    xs = [0.0]  # truck 0's position; followers' are their plants'
    followers: list[_Follower] = []
    for i in range(1, n_trucks):

        def range_fn(t: float, ego_x: float, i: int = i) -> float | None:
            ahead = xs[0] if i == 1 else followers[i - 2].plant.x
            return max(ahead - ego_x, 0.0)

        followers.append(_Follower(setup, pcfg, -i * gap0, sc.v0, range_fn))
    tr = PlatoonTrace()
    cycles = max(1, round(dur / dt))
    for k in range(cycles):
        t = k * dt
        v_lead, a_lead = sc.lead_v(t), sc.lead_a(t)
        channels[0].send(t, kinematic_plan(t, k, dt, v_lead, a_lead, n, "truck0"))
        for i, f in enumerate(followers, start=1):
            f.cycle(t, channels[i - 1].receive(t))
            if i < n_trucks - 1:
                assert f.out is not None
                own = cycle_plan(f.cyc, f.out, t, f"truck{i}")
                if own is not None:
                    channels[i].send(t, own)
        _record(tr, t, xs[0], v_lead, a_lead, followers, cfg.d_0)
        xs[0] += 0.5 * (v_lead + sc.lead_v(t + dt)) * dt
        for f in followers:
            f.fw.step(dt)
    return platoon_metrics(sc.name, n_trucks, tr, followers, channels, pcfg), tr


def _record(
    tr: PlatoonTrace,
    t: float,
    x_lead: float,
    v_lead: float,
    a_lead: float,
    followers: list[_Follower],
    d_0: float,
) -> None:
    tr.t.append(t)
    xs, vs, gaps, refs, hs, modes, us, acc = (
        [x_lead], [v_lead], [math.nan], [math.nan], [math.nan], ["LEAD"], [0.0], [a_lead]
    )  # fmt: skip
    for f in followers:
        assert f.dec is not None and f.out is not None
        gap = xs[-1] - f.plant.x
        xs.append(f.plant.x)
        vs.append(f.plant.v)
        gaps.append(gap)
        refs.append(d_0 + f.dec.headway * f.plant.v)
        hs.append(f.dec.headway)
        modes.append(f.dec.mode)
        us.append(f.out.command.voltage)
        acc.append(math.nan)
    tr.x.append(xs)
    tr.v.append(vs)
    tr.gap.append(gaps)
    tr.gap_ref.append(refs)
    tr.headway.append(hs)
    tr.mode.append(modes)
    tr.u.append(us)
    tr.accel.append(acc)
    tr.supervisor.append([f.out.mode.value for f in followers if f.out is not None])
    if not tr.rows:
        tr.rows = [[] for _ in followers]
    for j, f in enumerate(followers):
        assert f.out is not None
        tr.rows[j].append(
            (*f.cyc.log_row(f.out), f.plant.v, gaps[j + 1], vs[j], f.plant.x, f.plant.motor.i)
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
    followers: list[_Follower],
    channels: list[PlanChannel],
    pcfg: PlatoonConfig,
) -> dict[str, Any]:
    """The contract keys (reference section 1) plus switch times and decelerations."""
    t = np.asarray(tr.t)
    gaps = np.asarray(tr.gap, dtype=float)[:, 1:]
    err = gaps - np.asarray(tr.gap_ref, dtype=float)[:, 1:]
    keep = t >= SETTLE_S if len(t) and t[-1] >= 2.0 * SETTLE_S else np.ones(len(t), dtype=bool)
    l2, mx = string_ratios(err[keep])
    modes = np.asarray(tr.mode)[:, 1:]
    v = np.asarray(tr.v, dtype=float)
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    accel = np.diff(v, axis=0) / dt
    min_gap = float(np.min(gaps))
    first_acc = [
        float(t[np.argmax(modes[:, j] == ACC)]) if np.any(modes[:, j] == ACC) else None
        for j in range(modes.shape[1])
    ]
    return {
        "scenario": name,
        "trucks": n_trucks,
        "collision": bool(min_gap <= 0.0),
        "min_gap_m": min_gap,
        "string_ratio_l2": l2,
        "string_ratio_max": mx,
        "cacc_fraction": [float(np.mean(modes[:, j] == CACC)) for j in range(modes.shape[1])],
        # Extensions:
        "min_gap_per_follower_m": [float(np.min(gaps[:, j])) for j in range(gaps.shape[1])],
        "spacing_error_max_m": [float(np.max(np.abs(err[keep, j]))) for j in range(err.shape[1])],
        "first_acc_s": first_acc,
        "mode_switches": [f.mode.switches for f in followers],
        "min_accel_m_s2": [float(np.min(accel[keep[1:], j])) for j in range(1, accel.shape[1])],
        "cacc_headway_s": pcfg.cacc_headway,
        "acc_headway_s": pcfg.acc_headway,
        "plans_sent": sum(c.sent for c in channels),
        "plans_lost": sum(c.lost for c in channels),
        "solver_failures": [f.cyc.controller.solver_failures for f in followers],
        "supervisor_modes": [sorted(set(m)) for m in zip(*tr.supervisor, strict=True)],
        "duration_s": round(float(t[-1] + dt), 6),
    }
