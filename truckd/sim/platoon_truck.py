"""One simulated truck of a platoon (``truckd sim --platoon``): plant, simulated firmware
and the daemon's companion cycle with the platoon's part around it; its plan sources
(predecessor and standby, each with its clock estimate); and the drawn trucks of a mixed
platoon."""

from __future__ import annotations

import random
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from truckd.control.config import ControlConfig
from truckd.control.estimator import Estimate
from truckd.control.platoon import (
    CACC,
    Plan,
    PlatoonConfig,
    PlatoonDecision,
    PlatoonMode,
)
from truckd.control.qp import ControlModel
from truckd.io.port import companion_port
from truckd.model.params import VehicleParams
from truckd.runtime.cycle import CompanionCycle, CycleInputs, CycleOutputs
from truckd.runtime.platoon_follow import Follow, PlanSource
from truckd.runtime.platoon_link import follower_inputs
from truckd.sim.closed_loop import SimSetup
from truckd.sim.truck import build_truck

MIXED_EFFECTS: tuple[tuple[str, float, float], ...] = (
    ("viscous_friction", 0.0, 3e-5),
    ("aero_drag", 0.0, 0.8),
    ("load_force", 0.0, 1.5),
    ("battery_sag", 0.0, 0.05),
    ("dead_zone", 0.0, 0.4),
)
"""``--mixed``: the effects a truck draws one of, and its range (SI, truckd/model/effects.py)."""

MIXED_BLOCK_TAU = 0.3
"""``control.block_tau_fraction`` of every drawn truck (0.5 left the quickest trucks
behind: docs/platoon.md, "Mixed trucks")."""


def draw_platoon_truck(setup: SimSetup, rng: random.Random) -> SimSetup:
    """A truck of a mixed platoon: mass 0.6-2x the configured (the inertia reflected to the
    motor with it), motor constant 0.8-1.3x (friction torques with it), armature
    resistance 0.8-1.5x, and one effect of :data:`MIXED_EFFECTS` at a drawn magnitude
    (:func:`scaled_truck`)."""
    mass = rng.uniform(0.6, 2.0)
    k = rng.uniform(0.8, 1.3)
    r = rng.uniform(0.8, 1.5)
    name, lo, hi = MIXED_EFFECTS[rng.randrange(len(MIXED_EFFECTS))]
    return scaled_truck(setup, mass, k, r, (name, rng.uniform(lo, hi)))


def scaled_truck(
    setup: SimSetup,
    mass: float = 1.0,
    k: float = 1.0,
    r: float = 1.0,
    effect: tuple[str, float] | None = None,
) -> SimSetup:
    """The configured truck with its mass times ``mass`` (the inertia reflected to the
    motor with it), its motor constant times ``k`` (friction torques with it), its
    armature resistance times ``r``, and ``effect`` (name, magnitude in SI) set.  Its
    controller's model is this truck itself (its true parameters and effects, as a
    perfect ``diagnose`` would give them); its rate weight and input blocks are fitted to
    it (below)."""
    p = setup.plant_params
    m = p.m * mass
    reflected = p.ratio**2  # (r_w / (n_g n_fd))^2: kg at the wheel -> kg m^2 at the motor
    q = p.replace(
        m=m,
        J_S=max(p.J_S + (m - p.m) * reflected, 0.2 * p.J_S),
        K_v=p.K_v * k,
        K_T=p.K_T * k,
        K_coulomb=p.K_coulomb * k,
        K_stiction=p.K_stiction * k,
        R_m=p.R_m * r,
    )
    eff = setup.plant_config.effects
    if effect is not None:
        eff = replace(eff, **{effect[0]: effect[1]})
    return replace(
        setup,
        control=tuned_control(setup.control, p, q),
        plant_params=q,
        plant_config=replace(setup.plant_config, effects=eff),
        model=ControlModel(q, eff),
    )


def tuned_control(
    control: ControlConfig, configured: VehicleParams, model: VehicleParams
) -> ControlConfig:
    """``control`` (the configured truck's) for a truck whose controller's model has the
    parameters ``model``: tuned in acceleration, not volts.  The rate weight ``r_du`` is
    scaled by the square of the acceleration a volt gives (``K_T / (R_m J_S)``, against
    ``configured``), so every truck responds alike; the input blocks are at most
    :data:`MIXED_BLOCK_TAU` of the model's mechanical time constant, so every truck's plan
    can hold a deceleration alike (docs/platoon.md, "Mixed trucks").  Only the model is
    used: a controller on a diagnosed model is tuned to what was diagnosed."""
    q, p = model, configured
    gain = (q.K_T / (q.R_m * q.J_S)) / (p.K_T / (p.R_m * p.J_S))
    return replace(control, r_du=control.r_du * gain**2, block_tau_fraction=MIXED_BLOCK_TAU)


DIAGNOSED_DISTURBANCE_GAIN = 0.03
"""``control.disturbance_gain`` (at least) of a controller on a diagnosed model: the
offset-free action takes up what the diagnosis did not name (aero drag, small load forces,
viscous friction folded into the back-EMF), which otherwise leaves each such truck a
spacing offset of its own that changes with its speed (docs/platoon.md)."""

DIAGNOSED_MOVE_BLOCKS = 0
"""``control.move_blocks`` of a controller on a diagnosed model: one input per MPC step
(the sparse QP), instead of blocks cut to the model's mechanical time constant
(:data:`MIXED_BLOCK_TAU`), which a diagnosed model gives as an effective one (viscous
friction folded into the back-EMF, aero drag into a straight line).  Measured on 10 drawn
trucks, seeds 1-9, brake: largest ratio 1.015 instead of 1.092, 4 pairs above 1 instead
of 9; on the true parameters the blocks are the better (docs/platoon.md, "One input per
step on a diagnosed model")."""


def on_model(base: SimSetup, truck: SimSetup, model: ControlModel) -> SimSetup:
    """``truck`` (its plant stays) with its controller on ``model`` (a diagnosed one), tuned
    to that model (:func:`tuned_control` from ``base``'s configuration and truck), with the
    offset-free action on (:data:`DIAGNOSED_DISTURBANCE_GAIN`) and one input per step
    (:data:`DIAGNOSED_MOVE_BLOCKS`)."""
    control = tuned_control(base.control, base.plant_params, model.params)
    gain = max(control.disturbance_gain, DIAGNOSED_DISTURBANCE_GAIN)
    control = replace(control, disturbance_gain=gain, move_blocks=DIAGNOSED_MOVE_BLOCKS)
    return replace(truck, control=control, model=model)


class PlatoonTruck:
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
        t0: float = 0.0,
        events: list[tuple[float, str]] | None = None,
    ) -> None:
        """``x0`` (m) and ``v0`` (m/s) the truck's position and speed at ``t0`` (s, the
        plant's clock at the start: before 0 with a pre-roll); ``events``: the run's list
        of joins and leaves."""
        self.vid = vid
        cfg = setup.control
        spec = setup.truck
        truck = build_truck(spec, range_fn, v0=v0, x0=x0, t0=t0)
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
        self.follow = Follow(vid, predecessor, self.mode, cfg.d_0, t0, events)
        """Whom it follows (predecessor, standby, their plans): the daemon's order."""
        self.lane = 0
        self.active = True
        self.announce = True
        """Publishes its plans (a truck about to join in the middle is silent until it
        announces)."""
        self.out: CycleOutputs | None = None
        self.dec: PlatoonDecision | None = None
        self.order: Callable[[Estimate], bool] | None = None
        """Who to follow, given this cycle's estimate; True when the predecessor changed
        (None: a fixed predecessor)."""
        self._sync = True
        self._now = 0.0
        self.cyc.controller.redecide = self._on_estimate

    @property
    def predecessor(self) -> str:
        return self.follow.predecessor

    @property
    def source(self) -> PlanSource:
        return self.follow.source

    @property
    def standby(self) -> PlanSource:
        return self.follow.standby

    def _on_estimate(self, est: Estimate) -> tuple[list[float] | None, float] | None:
        """Between the estimate and the control law: a new vehicle ahead is seen by the
        order and the controller in the same cycle (no step on a stale headway)."""
        if self.order is not None and self.order(est):
            return self._redecide()
        return None

    def _redecide(self) -> tuple[list[float] | None, float]:
        """After a change of predecessor within the cycle: the new headway and forecast."""
        fc, headway = self.follow.redecide(self._sync, self._now)
        if self.dec is not None:
            self.dec = replace(self.dec, headway=headway, forecast=fc)
        return fc, headway

    def own(self, t: float) -> float:
        """This truck's clock at simulated time t (s)."""
        return self.clock_offset + (1.0 + self.clock_drift) * t

    def plan_in(self, sync: bool) -> Plan | None:
        """The predecessor's newest plan on this truck's clock (as received when the
        clocks are taken as synchronised)."""
        return self.follow.source.on_own_clock(sync)

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


def with_delay(s: SimSetup, delay: float) -> SimSetup:
    pc, model = s.plant_config, s.model
    d = max(pc.effects.input_delay, delay)
    return replace(
        s,
        plant_config=replace(pc, effects=replace(pc.effects, input_delay=d)),
        model=replace(model, effects=replace(model.effects, input_delay=d)),
    )


def drawn_summary(s: SimSetup) -> dict[str, Any]:
    p, eff = s.plant_params, s.plant_config.effects
    return {
        "m": p.m,
        "K_v": p.K_v,
        "R_m": p.R_m,
        "effects": {n: getattr(eff, n) for n in eff.active()},
    }
