"""The ``control:`` section of the configuration: MPC, limits, feedforward, estimator.

All SI.  The MPC's prediction step is the control period ``1 / rate_hz``; the daemon's
loop must run at the same rate (the :class:`~truckd.control.controller.Controller`
checks the time stamps it is given, not a clock).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from truckd.schema import spec


@dataclass(frozen=True)
class EstimatorConfig:
    """Own speed from encoder ticks; gap and lead speed from the range sensor."""

    def validate(self) -> str | None:
        """Cross-field checks."""
        if self.range_min >= self.range_max:
            return (
                f"range_min ({self.range_min}) must be below range_max ({self.range_max}): "
                "else no reading is ever a target"
            )
        return None

    ticks_modulo: int = spec(
        "encoder counters wrap at this value (2^16 in the firmware protocol)",
        lo=2,
        hi=2**32,
        default=65536,
    )
    sample_time_modulo: float = spec(
        "the firmware's sample clock wraps at this value",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=1e9,
        default=6.5536,
    )
    speed_accel_std: float = spec(
        "own-speed filter: acceleration process noise (std)",
        unit="m/s^2",
        lo=0.0,
        lo_open=True,
        hi=1e3,
        default=2.0,
    )
    encoder_timeout_s: float = spec(
        "own speed is stale after this long without a new encoder sample",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.05,
    )
    speed_max: float = spec(
        "own-speed filter: a step between two encoder samples faster than this is no "
        "motion but a discontinuity (counters reset or jumped): the filter restarts",
        unit="m/s",
        lo=0.0,
        lo_open=True,
        hi=1e3,
        default=15.0,
    )
    accel_max: float = spec(
        "own-speed filter: a step between two encoder samples whose speed differs from the "
        "filter's by more than this acceleration allows (plus the ticks' quantisation) is a "
        "discontinuity, not motion: the filter restarts; raised to the controller model's "
        "stall acceleration K_T u_max / (R_m J_S) at the wheels where that is higher",
        unit="m/s^2",
        lo=0.0,
        lo_open=True,
        hi=1e4,
        default=30.0,
    )
    range_max: float = spec(
        "range sensor maximum range: beyond it there is no lead",
        unit="m",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=4.0,
    )
    range_min: float = spec(
        "range sensor minimum range: a valid reading below it is taken as this (a target "
        "closer than the sensor resolves, not no target)",
        unit="m",
        lo=0.0,
        hi=10.0,
        default=0.02,
    )
    range_noise_std: float = spec(
        "range measurement noise (std)", unit="m", lo=0.0, lo_open=True, hi=1.0, default=0.01
    )
    lead_accel_std: float = spec(
        "lead filter: lead acceleration process noise (std)",
        unit="m/s^2",
        lo=0.0,
        lo_open=True,
        hi=1e3,
        default=1.5,
    )
    gate_sigma: float = spec(
        "innovation gate: readings further than this many std away are outliers",
        lo=1.0,
        hi=100.0,
        default=4.0,
    )
    reinit_count: int = spec(
        "consecutive mutually consistent outliers that mean a new target (cut-in)",
        lo=1,
        hi=100,
        default=3,
    )
    lead_timeout_s: float = spec(
        "the lead is lost after this long without an accepted reading",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=10.0,
        default=0.3,
    )


@dataclass(frozen=True)
class ControlConfig:
    """Adaptive cruise control: MPC on the identified model plus friction feedforward."""

    rate_hz: float = spec(
        "control rate; the MPC step is its period", unit="Hz", lo=1.0, hi=2000.0, default=100.0
    )
    horizon: int = spec(
        "MPC horizon (steps; above 200 OSQP fails to converge in some cycles)",
        lo=2,
        hi=200,
        default=40,
    )
    move_blocks: int = spec(
        "inputs held over this many blocks of the horizon (1, 1, 2, 4, .. steps) and the QP "
        "condensed to them; 0 = one input per step, the sparse QP (see docs/controller.md)",
        lo=0,
        hi=500,
        default=8,
    )
    block_tau_fraction: float = spec(
        "no input block longer than this share of the model's mechanical time constant "
        "J_S R_m / (K_T K_v): longer blocks are split (more blocks; another shape than the "
        "compiled cycle's runs the Python path).  A held voltage decays to the speed it "
        "drives at with that time constant: a truck whose constant is short against the "
        "blocks cannot hold a deceleration in its plan and tracks a braking lead looser "
        "than its predecessor (docs/platoon.md, mixed trucks).  0: no limit",
        lo=0.0,
        hi=10.0,
        default=0.0,
    )
    d_0: float = spec(
        "standstill gap of the spacing policy", unit="m", lo=0.0, hi=10.0, default=0.4
    )
    time_headway: float = spec(
        "time headway h of the spacing policy d_ref = d_0 + h v",
        unit="s",
        lo=0.0,
        hi=10.0,
        default=0.6,
    )
    d_min: float = spec(
        "hard minimum gap (soft constraint in the QP, heavy penalty)",
        unit="m",
        lo=0.0,
        hi=10.0,
        default=0.15,
    )
    v_set: float = spec(
        "set speed (cruise)", unit="m/s", lo=0.0, lo_open=True, hi=50.0, default=1.8
    )
    v_max: float = spec("speed limit", unit="m/s", lo=0.0, lo_open=True, hi=50.0, default=2.4)
    u_max: float = spec(
        "armature voltage limit |u| (at most the battery voltage)",
        unit="V",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=7.2,
    )
    du_max: float = spec(
        "armature voltage rate limit", unit="V/s", lo=0.0, lo_open=True, hi=1e6, default=400.0
    )
    q_gap: float = spec("weight on gap error^2", unit="1/m^2", lo=0.0, hi=1e9, default=30.0)
    q_rel_speed: float = spec(
        "weight on (v + T a - v_lead)^2 when following (T: rel_speed_lookahead; 0: the "
        "relative speed)",
        unit="s^2/m^2",
        lo=0.0,
        hi=1e9,
        default=5.0,
    )
    rel_speed_lookahead: float = spec(
        "T of the follow term q_rel_speed (v + T a - v_lead)^2, a the truck's own predicted "
        "acceleration: 0 weighs the relative speed; the time headway weighs the spacing "
        "error's rate (the gap then follows d_0 + h v through speed changes); a platoon "
        "follower's is set by platoon.spacing_rate",
        unit="s",
        lo=0.0,
        hi=10.0,
        default=0.0,
    )
    q_cruise: float = spec(
        "weight on (v - v_set)^2 when cruising",
        unit="s^2/m^2",
        lo=0.0,
        lo_open=True,
        hi=1e9,
        default=20.0,
    )
    r_du: float = spec(
        "weight on (u[k] - u[k-1])^2", unit="1/V^2", lo=0.0, lo_open=True, hi=1e9, default=5.0
    )
    slack_linear: float = spec(
        "linear penalty on constraint slack (exact penalty)", lo=0.0, hi=1e12, default=1e2
    )
    slack_quadratic: float = spec(
        "quadratic penalty on constraint slack", lo=0.0, lo_open=True, hi=1e12, default=1e2
    )
    follow_window: float = spec(
        "follow the lead when gap - d_ref is below this (else cruise, min gap still kept)",
        unit="m",
        lo=0.0,
        hi=100.0,
        default=1.0,
    )
    on_lead_lost: str = spec(
        "what to do when the lead is lost", choices=("cruise", "stop"), default="cruise"
    )
    time_budget_s: float = spec(
        "solver time budget per cycle (OSQP time_limit)",
        unit="s",
        lo=0.0,
        lo_open=True,
        hi=1.0,
        default=0.004,
    )
    max_iter: int = spec("OSQP iteration limit per solve", lo=1, hi=100_000, default=1000)
    eps: float = spec(
        "OSQP absolute and relative tolerance", lo=0.0, lo_open=True, hi=1.0, default=5e-5
    )
    plan_hold_steps: int = spec(
        "fallback: follow the shifted previous plan for at most this many cycles",
        lo=0,
        hi=1000,
        default=10,
    )
    brake_gain: float = spec(
        "fallback braking law: voltage per speed, u = -gain v",
        unit="V s/m",
        lo=0.0,
        hi=1e3,
        default=3.0,
    )
    feedforward: bool = spec("friction feedforward on", default=True)
    stiction_margin: float = spec(
        "breakaway feedforward as a multiple of the stiction voltage", lo=1.0, hi=3.0, default=1.1
    )
    moving_speed: float = spec(
        "speed above which the truck counts as moving",
        unit="m/s",
        lo=0.0,
        lo_open=True,
        hi=1.0,
        default=0.02,
    )
    start_voltage: float = spec(
        "at rest, an MPC command above this starts the truck (breakaway feedforward)",
        unit="V",
        lo=0.0,
        hi=10.0,
        default=0.05,
    )
    hold_gap_tol: float = spec(
        "standstill hold: entered at rest behind a (nearly) stopped lead when the gap is at "
        "most d_0 + this; the motor is then held at 0 V (no MPC, no breakaway)",
        unit="m",
        lo=0.0,
        hi=1.0,
        default=0.05,
    )
    hold_release_gap: float = spec(
        "standstill hold: left (start with the breakaway feedforward) when the gap exceeds "
        "d_0 + this (above hold_gap_tol: hysteresis)",
        unit="m",
        lo=0.0,
        lo_open=True,
        hi=2.0,
        default=0.1,
    )
    hold_lead_speed: float = spec(
        "standstill hold: entered only when the lead's estimated speed is at most this",
        unit="m/s",
        lo=0.0,
        hi=1.0,
        default=0.04,
    )
    hold_release_speed: float = spec(
        "standstill hold: left when the lead's estimated speed exceeds this (above "
        "hold_lead_speed: hysteresis)",
        unit="m/s",
        lo=0.0,
        lo_open=True,
        hi=2.0,
        default=0.08,
    )
    hold_release_cycles: int = spec(
        "standstill hold: a release condition must hold this many consecutive cycles",
        lo=1,
        hi=100,
        default=3,
    )
    disturbance_gain: float = spec(
        "offset-free action: integrator gain per cycle on the voltage disturbance the model "
        "lacks (0 = off: the controller relies on its model alone)",
        lo=0.0,
        hi=1.0,
        default=0.0,
    )
    disturbance_max: float = spec(
        "limit of the estimated voltage disturbance", unit="V", lo=0.0, hi=100.0, default=2.0
    )
    estimator: EstimatorConfig = spec("state estimation", default_factory=EstimatorConfig)

    @property
    def period(self) -> float:
        """Control period and MPC step (s)."""
        return 1.0 / self.rate_hz

    def in_simulated_time(self) -> ControlConfig:
        """This configuration for simulated time: no wall-clock budget (OSQP's time limit
        and the run-time check off); a solve is judged by what it did (status, iterations
        up to ``max_iter``), so the result does not depend on the machine's load.  On the
        car the budget stays."""
        return dataclasses.replace(self, time_budget_s=math.inf)

    def validate(self) -> str | None:
        """Cross-field checks."""
        if self.d_min >= self.d_0:
            return f"d_min ({self.d_min}) must be below the standstill gap d_0 ({self.d_0})"
        if self.hold_release_gap <= self.hold_gap_tol:
            return (
                f"hold_release_gap ({self.hold_release_gap}) must exceed hold_gap_tol "
                f"({self.hold_gap_tol})"
            )
        if self.hold_release_speed <= self.hold_lead_speed:
            return (
                f"hold_release_speed ({self.hold_release_speed}) must exceed hold_lead_speed "
                f"({self.hold_lead_speed})"
            )
        if self.v_set > self.v_max:
            return f"v_set ({self.v_set}) must not exceed v_max ({self.v_max})"
        return None
