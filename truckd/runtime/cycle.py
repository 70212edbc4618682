"""One companion cycle, pure: time and the checked messages in; sensor state -> controller
-> supervisor -> motor command out, plus what is published and what is recorded.

The same step runs everywhere the controller drives: the daemon on the car (``truckd run``
is only the I/O around it: poll, send, publish, record, keep rate), ``truckd sim`` in
simulated time, the replay of a recorded log and the benchmarks.  No I/O and no clock in
here: the caller passes its time; the solver's own run time comes back as data.

Extension points (platooning adds the predecessor's plan in and the own plan out):
:class:`CycleInputs` has ``lead_forecast`` (the lead's speed over the MPC horizon, e.g.
from the truck ahead's plan) and :meth:`CompanionCycle.plan` gives the controller's
predicted trajectory of this cycle.

Another command source (``truckd characterize``): :attr:`CompanionCycle.command_source`,
when set, is asked for the voltage instead of the controller (whose estimator still runs):
the supervisor, the SAFE_STOP ramp, the limits and the heartbeat stay as they are, so a
routine that drives the truck is one more source of commands for the one cycle, not a
second loop.  Its output's ``mode`` is ``external`` (no MPC solved).

Time budget: on the car (``time_budget=True``) a solve slower than
``control.time_budget_s`` is a failure (the controller falls back); in simulated time
(``time_budget=False``) the solver is judged only by what it did (status, iterations,
``control.max_iter``), so the result does not depend on how loaded the machine is; its
wall time is still measured and reported.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from firmware_protocol.messages import CompanionHeartbeat, CompanionState, MotorCommand
from firmware_protocol.timing import timing
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.estimator import EncoderSample, Estimate, RangeSample
from truckd.control.frozen import fast_init
from truckd.control.output import ControlOutput
from truckd.control.qp import ControlModel
from truckd.control.supervisor import (
    Decision,
    Mode,
    Supervisor,
    SupervisorConfig,
)
from truckd.io.port import Received
from truckd.runtime.command import motor_command
from truckd.runtime.sensors import SensorState

MODE_CODE = {Mode.INIT: 0, Mode.ACTIVE: 1, Mode.DEGRADED: 2, Mode.SAFE_STOP: 3, Mode.FAULT: 4}
"""Numeric mode in the CSV log (the log format is all numbers)."""

_MODE_CODE_F = {m._value_: float(code) for m, code in MODE_CODE.items()}
""":data:`MODE_CODE` as floats, keyed by the mode's text (a ``str``'s hash; the enum's own
``__hash__`` is a Python call)."""

LOG_COLUMNS = (
    "t", "u", "v", "i", "vbat", "x", "gap", "v_lead",  # the contract's (reference section 3)
    "gap_ref", "u_ff", "u_fw", "solve_us", "mode", "enable",
    "lead_valid", "range_raw", "seq",
)  # fmt: skip
"""Columns of :meth:`CompanionCycle.log_row`: the contract's names first, then extras.
``gap`` and ``v_lead`` are the estimates, NaN while no lead is tracked; ``solve_us`` is
OSQP's own run time of this cycle's solve (NaN when the controller raised)."""

HEARTBEAT_PERIOD_S = timing().heartbeat_period
"""The companion heartbeat's period (truck.dbc's ``GenMsgCycleTime``: 100 ms)."""


class CommandSource(Protocol):
    """Another source of the motor voltage (see the module docstring)."""

    def __call__(self, t: float, est: Estimate, sensors: SensorState) -> float:
        """The voltage (V) this cycle at time ``t`` (s since the start), given the
        estimate and the sensor state of this cycle; a non-finite one is sent as 0 V."""
        ...


@dataclass(frozen=True, slots=True)
class CycleInputs:
    """What one cycle takes.

    ``now``: the caller's time (s), the clock that stamped ``received``; ``received``: the
    checked messages since the last cycle, oldest first; ``link_up``: the transport is
    connected; ``loop_missed``: the previous cycle missed its deadline (the rate keeper's
    verdict on the car; always False in simulated time); ``lead_forecast``: optional
    lead speed over the MPC horizon (m/s per step), replacing the constant-speed
    prediction (the predecessor's plan in a platoon); ``headway``: optional time headway
    (s) replacing the configured one (the platoon's CACC/ACC headway).
    """

    now: float
    received: Sequence[Received] = ()
    link_up: bool = True
    loop_missed: bool = False
    lead_forecast: Sequence[float] | None = None
    headway: float | None = None


@dataclass(frozen=True, slots=True)
class Plan:
    """The controller's predicted trajectory: step ``dt`` (s), speed ``v`` (m/s, from now:
    one point per command still in the input delay's pipeline, then the QP's N+1) and
    acceleration ``a`` (m/s^2, one fewer)."""

    dt: float
    v: tuple[float, ...]
    a: tuple[float, ...]


@fast_init
@dataclass(frozen=True)
class CycleOutputs:
    """What one cycle produces.

    ``seq`` cycle number from 0; ``t`` s since the start; ``command`` the motor command
    to send (always finite, within limits); ``heartbeat`` the companion heartbeat to send
    this cycle (every 100 ms) or None; ``decision`` the supervisor's mode and causes;
    ``control`` the controller's output (None when it raised: ``error`` says why);
    ``ages`` seconds since the last valid message of each kind.
    """

    seq: int
    t: float
    command: MotorCommand
    heartbeat: CompanionHeartbeat | None
    decision: Decision
    control: ControlOutput | None
    ages: dict[str, float]
    error: str | None = None
    stall_s: float = 0.0
    """The loop stall detected at this cycle (s since the previous one; 0: none)."""

    @property
    def mode(self) -> Mode:
        return self.decision.mode


def state_message(out: CycleOutputs, lateness_s: float = 0.0) -> dict[str, Any]:
    """The published state of the cycle ``out`` (reference section 5); ``lateness_s``
    the loop's.  Reads only ``out`` (frozen): safe on another thread, later."""
    c = out.control
    isfinite = math.isfinite
    cmd, dec = out.command, out.decision
    # A non-finite number is null (truckd.jsonsafe.json_number, written out here: a call
    # per value costs more than the test itself).
    v: float | None
    gap: float | None
    gap_ref: float | None
    v_lead: float | None
    u_ff: float | None
    solve_us: float | None
    mode: str | None
    fallback: str | None
    if c is None:
        v = gap = gap_ref = v_lead = u_ff = solve_us = mode = None
        lead_valid, fallback = False, "exception"
    else:
        est = c.estimate
        v, gap, gap_ref, v_lead = est.v, est.gap, c.gap_ref, est.v_lead
        v = v if isfinite(v) else None
        gap = gap if isfinite(gap) else None
        gap_ref = gap_ref if isfinite(gap_ref) else None
        v_lead = v_lead if isfinite(v_lead) else None
        u_ff, solve_us = c.u_ff, c.solve_time_s * 1e6
        u_ff = u_ff if isfinite(u_ff) else None
        solve_us = solve_us if isfinite(solve_us) else None
        lead_valid, mode, fallback = bool(est.lead_valid), c.mode, c.fallback_reason
    ages: dict[str, float | None] = {}
    for k, a in out.ages.items():
        ms = a * 1e3
        ages[k] = ms if isfinite(ms) else None
    return {
        "seq": out.seq,
        "t": out.t,
        "mode": dec.mode._value_,
        "v": v,
        "gap": gap,
        "gap_ref": gap_ref,
        "v_lead": v_lead,
        "u": cmd.voltage,
        "u_ff": u_ff,
        "solve_us": solve_us,
        "enable": cmd.enable,
        "ctrl": mode,
        "fallback": fallback,
        "lead_valid": lead_valid,
        "lateness_us": lateness_s * 1e6,
        "faults": list(dec.causes),
        "ages_ms": ages,
    }


class CompanionCycle:
    """The companion's state across cycles and the step between them (module docstring).

    ``t0`` (s, the caller's clock) is the start: ``t = now - t0``.  ``stop_ramp_v_per_s``
    is the SAFE_STOP ramp towards 0 V.
    """

    def __init__(
        self,
        model: ControlModel,
        control: ControlConfig,
        supervisor: SupervisorConfig,
        ticks_per_rev: int,
        stop_ramp_v_per_s: float,
        *,
        time_budget: bool = True,
        t0: float = 0.0,
        stall_limit_s: float = math.inf,
    ) -> None:
        if not time_budget:
            control = control.in_simulated_time()
        self.control_cfg = control
        self.time_budget = time_budget
        self.controller = Controller(model, control, ticks_per_rev)
        self.supervisor = Supervisor(supervisor, control.on_lead_lost)
        self.sensors = SensorState(tick_len=self.controller.estimator.tick_len)
        self.u_max = self.controller.u_max
        self.period = control.period
        self.ramp_step = stop_ramp_v_per_s * self.period
        self.hb_every = max(1, round(HEARTBEAT_PERIOD_S / self.period))
        self.t0 = t0
        self.seq = 0
        self.u = 0.0
        self.enable = False
        self.controller_errors = 0
        self.stall_limit_s = stall_limit_s
        self._last_now: float | None = None
        self.stalls = 0
        """Loop stalls detected (a cycle later than ``stall_limit_s`` after the previous)."""
        self.last_stall_s = 0.0
        self.command_source: CommandSource | None = None
        """When set, the voltage comes from here instead of the controller."""

    def step(self, inp: CycleInputs) -> CycleOutputs:
        """One cycle: sensors -> controller -> supervisor -> motor command."""
        now = inp.now
        t = now - self.t0
        s = self.sensors
        s.update(now, inp.received)
        stall = now - self._last_now if self._last_now is not None else 0.0
        self._last_now = now
        encoders: Sequence[EncoderSample] = s.encoders
        ranges: Sequence[RangeSample] = s.ranges
        if stall > self.stall_limit_s:
            # The picture is old: restart the control state, keep the motor off until the
            # sensors are fresh again (the samples that queued meanwhile are not used).
            self.stalls += 1
            self.last_stall_s = stall
            self.controller.reinitialise()
            self.supervisor.restart(t)
            encoders, ranges = (), ()
        else:
            stall = 0.0
        error = None
        out: ControlOutput | None
        try:
            src = self.command_source
            if src is None:
                # The driver's feedback (current, battery) once one has arrived (vbat > 0).
                fed = s.vbat > 0.0
                out = self.controller.step(
                    t,
                    encoders,
                    ranges,
                    inp.lead_forecast,
                    inp.headway,
                    s.current if fed else math.nan,
                    s.vbat if fed else math.nan,
                )
            else:
                out = self._external(t, src, encoders, ranges)
        except Exception as exc:  # counted as a solver failure by the supervisor
            self.controller_errors += 1
            out, error = None, f"{type(exc).__name__}: {exc}"
        link_age, encoder_age, range_age = now - s.t_any, now - s.t_encoder, now - s.t_range
        ages = {"link": link_age, "encoder": encoder_age, "range": range_age}  # as s.ages(now)
        if out is None:
            # (an exception in the controller counts as a solver failure instead)
            speed, speed_age, lead_valid, solver_ok, u_ctrl = 0.0, 0.0, False, False, None
        else:
            est = out.estimate
            speed = est.v if est.speed_valid else 0.0
            speed_age, lead_valid, u_ctrl = est.speed_age, est.lead_valid, out.u
            reason = out.fallback_reason
            solver_ok = reason is None or not reason.startswith("solver_")
        # The supervisor's inputs (SupervisorInputs' fields) as arguments, positional: no
        # record built every cycle.
        dec = self.supervisor.decide(
            t, inp.link_up, link_age, encoder_age, range_age, s.range_raw, s.range_fault,
            speed, speed_age, lead_valid, solver_ok, inp.loop_missed, self.u,
        )  # fmt: skip
        mode = dec.mode
        self.u, self.enable = motor_command(mode, u_ctrl, self.u, self.ramp_step, self.u_max)
        self.controller.u_prev = self.u  # the rate limit starts from what is sent
        hb = (
            CompanionHeartbeat(CompanionState[mode._value_], 0)
            if self.seq % self.hb_every == 0
            else None
        )
        res = CycleOutputs(
            self.seq, t, MotorCommand(self.u, self.enable), hb, dec, out, ages, error, stall
        )
        self.seq += 1
        return res

    def _external(
        self,
        t: float,
        src: CommandSource,
        encoders: Sequence[EncoderSample],
        ranges: Sequence[RangeSample],
    ) -> ControlOutput:
        """The estimator as in :meth:`Controller.step` on this cycle's samples, the voltage
        from ``src`` (finite, within the controller's voltage limit), no MPC solve."""
        ctrl, s = self.controller, self.sensors
        est = ctrl.estimator.cycle(t, encoders, ranges)
        u = src(t, est, s)
        u = min(max(u, -self.u_max), self.u_max) if math.isfinite(u) else 0.0
        return ControlOutput(
            u=u, u_ff=0.0, u_mpc=u, mode="external", fallback_reason=None,
            solver_status="not-run", solve_iterations=0, solve_time_s=0.0, gap_ref=math.nan,
            estimate=est, solver_failures=ctrl.solver_failures,
            fallback_cycles=ctrl.fallback_cycles, overruns=ctrl.overruns,
            braking_cycles=ctrl.braking_cycles,
        )  # fmt: skip

    def plan_speeds(self, out: CycleOutputs) -> list[float] | None:
        """The predicted speeds (m/s, one per period from now) of the cycle ``out`` (call
        it before the next step): the speeds over the commands already in the pipeline
        (input delay), then the QP's, whose step 0 lies that many periods ahead; None when
        that cycle's MPC did not solve (hold, fallback)."""
        speeds = self.plan_speed_array(out)
        return None if speeds is None else speeds.tolist()

    def plan_speed_array(self, out: CycleOutputs) -> NDArray[np.float64] | None:
        """:meth:`plan_speeds` as a float64 array (the MPC's own when no command is in
        the pipeline: not to be changed)."""
        c = out.control
        speeds = self.controller.mpc.last_speeds
        if c is None or c.fallback_reason is not None or c.solve_iterations == 0 or speeds is None:
            return None
        pipe = self.controller.pipeline_v
        return np.array([*pipe, *speeds.tolist()]) if pipe else speeds

    def compiled_plan(self, speeds: NDArray[np.float64]) -> list[float] | None:
        """The plan of ``speeds``, what :meth:`plan_speed_array` gave for a cycle, as the
        compiled cycle made it: the speeds clipped at 0 (m/s), then their accelerations
        (m/s^2), ``N + 1`` each in one list, the same as
        :func:`~truckd.control.platoon.plan_of_array` makes of them; None unless they are
        the MPC's own speeds (no commands in the pipeline) of a compiled solve at this
        cycle's period."""
        mpc = self.controller.mpc
        plan = mpc.last_plan
        if plan is None or speeds is not mpc.last_speeds or mpc.cfg.period != self.period:
            return None
        values: list[float] = plan.tolist()
        return values

    def plan(self, out: CycleOutputs) -> Plan | None:
        """The controller's predicted trajectory of the cycle ``out`` (call it before the
        next step); None when that cycle's MPC did not solve (hold, fallback)."""
        vs = self.plan_speeds(out)
        if vs is None:
            return None
        dt = self.period
        return Plan(dt, tuple(vs), tuple((b - a) / dt for a, b in itertools.pairwise(vs)))

    def state_message(self, out: CycleOutputs, lateness_s: float = 0.0) -> dict[str, Any]:
        """The published state of the cycle ``out``: :func:`state_message`."""
        return state_message(out, lateness_s)

    def log_row(self, out: CycleOutputs) -> tuple[float, ...]:
        """The recorded row, in :data:`LOG_COLUMNS` order (sensor values as of this cycle)."""
        s = self.sensors
        c = out.control
        cmd = out.command
        range_raw = s.range_raw
        if c is None:
            nan = math.nan
            v, gap, v_lead, gap_ref, u_ff, solve_us, lead = 0.0, nan, nan, nan, nan, nan, 0.0
        else:
            est = c.estimate
            v = est.v if math.isfinite(est.v) else 0.0
            gap, v_lead, lead = est.gap, est.v_lead, float(est.lead_valid)
            gap_ref, u_ff, solve_us = c.gap_ref, c.u_ff, c.solve_time_s * 1e6
        return (
            out.t, cmd.voltage, v, s.current, s.vbat, s.x, gap, v_lead, gap_ref, u_ff, s.u_fw,
            solve_us, _MODE_CODE_F[out.decision.mode._value_], float(cmd.enable), lead,
            range_raw if range_raw is not None else math.nan, float(out.seq),
        )  # fmt: skip
