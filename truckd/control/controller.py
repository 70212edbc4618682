"""The controller the daemon calls once per cycle: plain inputs in, command out.

Each cycle: estimate (encoders, range) -> standstill hold or the MPC mode -> friction
feedforward (the model's known effects: :mod:`truckd.control.effect_use`) -> warm-started MPC
solve -> on failure the shifted previous plan, then a braking law -> limits (finite,
``|u| <= u_max``, rate limit, no reversing from rest) -> the driver's maps (battery sag, dead
zone; the current limit in the record of what acts).  Everything the
supervisor and telemetry need comes back in :class:`ControlOutput`.  No clock: the
caller passes its time ``t`` (s); the MPC step is the configured period.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Callable, Sequence

from truckd.control import ccycle, cestimator, cnumerics
from truckd.control.config import ControlConfig
from truckd.control.decisions import SATURATED_V, disturbance_update, hold_update, mode_of
from truckd.control.effect_use import (
    DeadZoneLaw,
    Winding,
    current_window,
    sag_command,
    sag_limit,
    startup_line,
    torque_terms,
)
from truckd.control.estimator import EncoderSample, Estimate, Estimator, RangeSample, for_truck
from truckd.control.fallback import braking_law, held_plan_move, limit_command
from truckd.control.feedforward import breakaway_feedforward, moving_feedforward
from truckd.control.lead import LeadSpeeds
from truckd.control.mpc import MpcResult, MpcSolver
from truckd.control.output import ControlOutput
from truckd.control.pipeline import predict_pipeline
from truckd.control.qp import ControlModel, QpInputs, Vec

__all__ = ["SATURATED_V", "Controller"]


class Controller:
    """Adaptive cruise control for one truck (see module docstring)."""

    def __init__(self, model: ControlModel, cfg: ControlConfig, ticks_per_rev: int) -> None:
        """``ticks_per_rev``: encoder ticks per wheel revolution (``TruckConfig.ticks_per_rev``:
        the configuration's, computed in one place)."""
        self.model, self.cfg = model, cfg
        self.mpc = MpcSolver(model, cfg)
        u_stall = min(cfg.u_max, model.params.V_batt)  # (V) the largest command at rest
        self.estimator_cfg = for_truck(cfg.estimator, model.params, u_stall)
        """The estimator's configuration for this model (``accel_max`` >= its stall accel)."""
        reference = Estimator(self.estimator_cfg, model.params.r_w, ticks_per_rev)
        compiled, self._estimator_why = cestimator.bind(
            self.mpc.compiled_cycle, self.estimator_cfg, reference.tick_len
        )
        self.estimator: Estimator | cestimator.CompiledEstimator = compiled or reference
        """The estimator: compiled with the MPC's compiled cycle, else the Python one."""
        self._ticks_per_rev = ticks_per_rev
        sat = model.effects.voltage_saturation
        self.u_max = min(cfg.u_max, model.params.V_batt, sat if sat > 0.0 else math.inf)
        self._delay_steps = round(model.effects.input_delay / cfg.period)
        self._sent: deque[float] = deque(maxlen=self._delay_steps + 1)
        self._du = cfg.du_max * cfg.period
        eff = model.effects
        self.dead_zone = DeadZoneLaw(eff.dead_zone, eff.dead_zone_offset)
        """The command map of a driver dead zone (see :mod:`truckd.control.effect_use`)."""
        self._terms = torque_terms(eff)
        """The feedforward torque terms of the model's effects (fixed: found once)."""
        self.winding = Winding(model.params, eff)
        """The winding's temperature and resistance (``resistance_drift``): not forgotten
        on :meth:`reinitialise` (the motor stays as warm as it was)."""
        self._r_scale = 1.0
        """The winding's resistance over ``R_m``: every feedforward voltage scales by it."""
        self.startup_note = startup_line(eff)
        """One line naming the effects of the model the controller cannot use (None: all
        used); the daemon and ``truckd sim`` log it at start-up."""
        self.solver_failures = self.fallback_cycles = self.overruns = self.braking_cycles = 0
        self._b_v = float(self.mpc.qp.pred.bu[1])
        """Speed per volt over one step (m/s/V), for the offset-free action."""
        self.lead_speeds = LeadSpeeds(cfg, self.mpc.horizon)
        """The lead's speeds the MPC is given (:mod:`truckd.control.lead`)."""
        self._numerics, self._numerics_why = cnumerics.bind(
            self.mpc, model, cfg, self.u_max, self._du, self._delay_steps, self._b_v, SATURATED_V
        )
        # The driver's maps and the winding model this model has (the others never called).
        self._sag, self._current_limit = not eff.battery_sag <= 0.0, not eff.current_limit <= 0.0
        self._dead_zone, self._drift = self.dead_zone.active, self.winding.active
        self._fused: tuple[cnumerics.CompiledNumerics, cestimator.CompiledEstimator] | None = None
        """The numerics and the estimator that run the estimator's update, the decisions
        and the solve in one call (:meth:`step`); None: not for this model (:attr:`backend`)."""
        if compiled is not None and self._numerics is not None and not self._drift:
            self._fused = (self._numerics, compiled)
        self.redecide: Callable[[Estimate], tuple[Sequence[float] | None, float] | None] | None
        self.redecide = None
        """Called with each cycle's estimate before the control law (a platoon's order); a
        result replaces the forecast and headway.  While set, no fused compiled call."""
        self._forget()

    @property
    def backend(self) -> str:
        """Which path computes the cycle's numerics and why (start-up log, health); a
        wrapped ``mpc.solve`` (fault injection, replay's recording) runs the Python path."""
        why = "the MPC's solve is wrapped" if "solve" in self.mpc.__dict__ else ""
        if self._numerics is None or why:
            why = why or self._numerics_why
            e_why = self._estimator_why
            est = f"estimator in Python ({e_why})" if e_why else "estimator compiled"
            return (
                f"MPC {self.mpc.backend}; feedforward and command checks in Python ({why}); {est}"
            )
        if self._fused is None or self.redecide is not None:
            why = "the winding model's resistance is Python's" if self._fused is None else ""
            return (
                "compiled (MPC, feedforward and command checks in one call; the estimator "
                f"in another: {why or 'a platoon order runs between the two'})"
            )
        return "compiled (estimator, decisions, MPC, feedforward and command checks in one call)"

    def _forget(self) -> None:
        """Set every state learned from past cycles to its start (the counters stay)."""
        self.u_prev = 0.0
        self.current = math.nan
        """The motor current (A) last measured (NaN: none), for the battery sag map."""
        self.vbat = math.nan
        """The battery voltage (V) last measured (NaN: none), for the battery sag map."""
        self.lead_speeds.reset()
        self._v_act = math.nan
        """The speed (m/s) predicted for when the planned command acts (NaN: none)."""
        self._wanted = 0.0
        """The motor voltage (V) the last command was meant to apply (before the maps)."""
        self._out = 0.0
        """The last command returned (V): while :attr:`u_prev` equals it, the voltage at
        the motor is :attr:`_wanted`."""
        self._plan: Vec | None = None
        self._plan_age = 0
        self.disturbance_v = 0.0
        """Estimated input-voltage disturbance (V), added to the feedforward."""
        self._v_expected = math.nan
        self.holding = False
        """Standstill hold active (see :func:`~truckd.control.decisions.hold_update`)."""
        self._release_cycles = 0
        self._limited = False
        """The last command was cut to the driver's current limit (no wind-up)."""
        self._sent.clear()
        self.dead_zone.reset()
        self.pipeline_v: list[float] = []
        """Speeds (m/s) predicted at ``now + k period`` for the commands already sent but
        not yet acting (the input delay): the QP's horizon starts after them.  Set by
        each solve; a published plan begins with them."""

    def reinitialise(self) -> None:
        """Forget the state learned from past cycles (after the loop stalled: it describes
        a world that has moved on): a new estimator, no MPC warm start, no held plan, no
        commands in the pipeline, no disturbance estimate, no standstill hold."""
        if isinstance(self.estimator, cestimator.CompiledEstimator):
            self.estimator = self.estimator.fresh()  # the library's state starts again
            self._fused = self._fused and (self._fused[0], self.estimator)
        else:
            r_w = self.model.params.r_w
            self.estimator = Estimator(self.estimator_cfg, r_w, self._ticks_per_rev)
        self.mpc.restart()
        self._forget()

    @property
    def forecast_steps(self) -> int:
        """Values a lead-speed forecast should have (one per period from now): the input
        delay's commands in the pipeline, then the MPC horizon."""
        return self._delay_steps + self.mpc.horizon

    def _pipeline_steps(self) -> int:
        """Commands sent but not yet acting (the QP's step 0 lies this many periods ahead)."""
        return max(len(self._sent) - 1, 0) if self._delay_steps > 0 else 0

    def step(
        self,
        t: float,
        encoders: Sequence[EncoderSample] = (),
        ranges: Sequence[RangeSample] = (),
        v_lead_forecast: Sequence[float] | None = None,
        headway: float | None = None,
        current: float = math.nan,
        vbat: float = math.nan,
    ) -> ControlOutput:
        """One cycle at caller time t (s) with the samples received since the last one
        (oldest first).

        ``v_lead_forecast`` (m/s at t + k period, k = 0, 1, ...; optional; see
        :attr:`forecast_steps`) replaces the constant-speed prediction of the lead, e.g. a
        plan received from the truck ahead: with an input delay its first values cover
        the commands already in the pipeline, the rest the QP's horizon.  ``headway``
        (s, optional) replaces the configured time headway (platooning, see
        :meth:`control`).  ``current`` (A) and ``vbat`` (V): the motor driver's last
        feedback (NaN: none), used by the battery sag map.
        """
        self.current, self.vbat = current, vbat
        fused = None if self.holding or v_lead_forecast is not None else self._fused
        if fused is None or self.redecide is not None or "solve" in self.mpc.__dict__:
            est = self.estimator.cycle(t, encoders, ranges)
            if self.redecide is not None and (again := self.redecide(est)) is not None:
                v_lead_forecast, headway = again
            return self.control(est, v_lead_forecast, headway)
        # The estimator's update, the decisions and the solve in one compiled call; it
        # stops after the estimate where the next decision is Python's (no valid speed,
        # the standstill hold begins): control() goes on from there.
        numerics, estimator = fused
        h = self.cfg.time_headway if headway is None else headway
        decisions = (
            h, self._applied_prev(), self._v_expected, 1.0 if self._limited else 0.0,
            self._wanted, self._u_hi(), self.disturbance_v, self._r_scale,
        )  # fmt: skip
        status, est = numerics.run_cycle(estimator, t, encoders, ranges, decisions)
        if status == ccycle.ESTIMATED:
            return self.control(est, v_lead_forecast, headway)
        mode_code, lead, gap_ref, self.disturbance_v = numerics.decisions_out.tolist()
        self._v_expected = math.nan  # (as control() sets it)
        if lead != 1.0:
            self.lead_speeds.reset_speed()
        res, out = numerics.outcome(status)
        mode = cnumerics.MODES[int(mode_code)]
        return self._compiled_output(est, est.v, res, out, mode, gap_ref)

    def control(
        self,
        est: Estimate,
        forecast: Sequence[float] | None = None,
        headway: float | None = None,
    ) -> ControlOutput:
        """The control law on a given estimate (the estimator bypassed, for tests).

        ``headway`` h (s) other than the configured one (the platoon's CACC/ACC headway,
        ramped between them): the reference gap is ``d_0 + h v``; the QP, whose cost is
        built with the configured headway, sees the gap less ``(h - time_headway) v``, so
        it drives the same spacing error without a new factorisation.

        The steps: the winding's thermal model (:meth:`_update_winding`); without a valid
        speed the fallback; the standstill hold, the mode and the offset-free action
        (:mod:`truckd.control.decisions`); the lead's speeds (:mod:`truckd.control.lead`);
        the plan and its first move (:meth:`_solve`), made a command by :meth:`_finish`
        (breakaway, limits, the driver's maps); or both at once compiled
        (:meth:`_solve_compiled`).
        """
        cfg = self.cfg
        v = est.v if math.isfinite(est.v) else 0.0
        if self._drift:
            self._update_winding(v)
        if not (est.speed_valid and math.isfinite(est.v)):
            # A non-finite speed said to be valid is no speed either: planning with 0 m/s
            # in its place would take a moving truck for one at rest.
            return self._fallback(est, v, "speed_stale", "fallback", math.nan, "not-run", 0, 0.0)
        lead = est.lead_valid and math.isfinite(est.gap) and math.isfinite(est.v_lead)
        h = cfg.time_headway if headway is None else headway
        gap_ref = cfg.d_0 + h * max(v, 0.0) if lead else math.nan  # reversing: d_0
        self.holding, self._release_cycles = hold_update(
            cfg, self.holding, self._release_cycles, est, v, lead
        )
        if self.holding:
            return self._hold(est, v, gap_ref)
        mode, v_ref = mode_of(cfg, est, lead, gap_ref)
        expected, self._v_expected = self._v_expected, math.nan
        self.disturbance_v = disturbance_update(
            cfg, self.disturbance_v, expected, v, self._limited, self._wanted, self.u_max,
            self._u_hi(), self._b_v,
        )  # fmt: skip
        n_pipe = self._pipeline_steps() if self._delay_steps > 0 else 0
        v_lead_all = self.lead_speeds.speeds(est, forecast, mode, lead, n_pipe)
        gap = est.gap - (h - cfg.time_headway) * v if lead else 0.0
        return self._solve(est, v, gap, v_lead_all, n_pipe, (mode, v_ref, lead), gap_ref)

    def _solve(
        self,
        est: Estimate,
        v: float,
        gap: float,
        v_lead_all: list[float],
        n_pipe: int,
        how: tuple[str, float, bool],
        gap_ref: float,
    ) -> ControlOutput:
        """The MPC's plan from the state when its first move acts, and the command from it
        (or the fallback's).  ``gap`` (m) as the QP sees it (the headway's share moved
        out), ``how``: the mode, the speed reference (m/s) and whether a lead is tracked."""
        if self._numerics is not None and "solve" not in self.mpc.__dict__:
            # (a solve wrapped on the instance, fault injection or a test's: Python path)
            return self._solve_compiled(est, v, gap, v_lead_all, how, gap_ref)
        cfg = self.cfg
        mode, v_ref, lead = how
        ff_now = self._feedforward(v, est.x)
        applied = self._applied_prev()
        v_lead_h = v_lead_all[n_pipe:]
        # With an input delay the plan's first command acts at the end of the pipeline:
        # the state, and the feedforward (speed, terrain), are those predicted there.
        x0, ff = self._initial_state(
            v, gap, ff_now, v_lead_all[:n_pipe] if n_pipe else v_lead_h[:1],
            held=abs(v) <= cfg.moving_speed or applied == ff_now, x_pos=est.x,
        )  # fmt: skip
        # At rest the previous voltage moved nothing (stiction), so to the friction-free
        # model it is 0 V: else the rate penalty keeps asking for it and the breakaway
        # feedforward kicks the truck forward again and again while it should stand.
        # (With an input delay: at rest when the first planned command acts.)
        self._v_act = x0[1]
        at_rest = abs(self._v_act) <= cfg.moving_speed
        # Positional, in the fields' order (see _finish): x0, u_prev, v_lead, lead, v_ref,
        # v_cap, u_lo, u_hi.
        u_prev = 0.0 if at_rest else applied - ff
        inp = QpInputs(
            x0, u_prev, v_lead_h, lead, v_ref, cfg.v_max, -self.u_max - ff, self._u_hi() - ff
        )
        res = self.mpc.solve("follow" if mode == "follow" else "cruise", inp)
        if not res.ok:
            return self._solver_failed(est, v, res, mode, gap_ref, ff)
        self._keep_plan(res)
        return self._finish(
            est, v, res.u0, ff, mode, None, res.status, res.iterations, res.run_time_s, gap_ref
        )

    def _solve_compiled(
        self,
        est: Estimate,
        v: float,
        gap: float,
        v_lead: list[float],
        how: tuple[str, float, bool],
        gap_ref: float,
    ) -> ControlOutput:
        """:meth:`_solve` and, from a usable solution, :meth:`_finish` in one compiled call
        (:mod:`truckd.control.cnumerics`; no input delay: ``v_lead`` is the horizon's):
        the same command.  A failed solve goes to :meth:`_fallback` with the feedforward
        the call computed."""
        assert self._numerics is not None
        mode, v_ref, lead = how
        applied = self._applied_prev()
        state = (v, gap, applied, self.disturbance_v, self._r_scale, self._u_hi(), v_ref)
        res, out = self._numerics.run(mode != "follow", lead, state, v_lead)
        return self._compiled_output(est, v, res, out, mode, gap_ref)

    def _compiled_output(
        self,
        est: Estimate,
        v: float,
        res: MpcResult,
        out: list[float],
        mode: str,
        gap_ref: float,
    ) -> ControlOutput:
        """The output of the compiled numerics' cycle: ``out`` their command, feedforward,
        voltage acting (V) and finished flag; a failed solve goes to :meth:`_fallback`."""
        u, ff, acting, finished = out
        if res.ok and finished != 1.0:  # the call and the outcome disagree: never its command
            res = dataclasses.replace(res, ok=False, status="unfinished")
        if not res.ok:
            self._v_act = v  # the speed when the command acts (no delay: now)
            return self._solver_failed(est, v, res, mode, gap_ref, ff)
        self._keep_plan(res)
        self._limited = False  # no current limit (cnumerics.unsupported)
        self.u_prev = self._out = u
        self._wanted = acting
        self._sent.append(acting)
        return ControlOutput(
            u, ff, u - ff, mode, None, res.status, res.iterations, res.run_time_s, gap_ref,
            est, self.solver_failures, self.fallback_cycles, self.overruns,
            self.braking_cycles, self.mpc.inaccurate, self.disturbance_v,
        )  # fmt: skip

    def _solver_failed(
        self, est: Estimate, v: float, res: MpcResult, mode: str, gap_ref: float, ff: float
    ) -> ControlOutput:
        """A failed solve counted and handed to :meth:`_fallback` (``ff``: feedforward, V)."""
        self.solver_failures += 1
        self.overruns += res.status == "overrun"
        return self._fallback(
            est, v, f"solver_{res.status}", mode, gap_ref, res.status, res.iterations,
            res.run_time_s, ff,
        )  # fmt: skip

    def _keep_plan(self, res: MpcResult) -> None:
        """A usable solve's plan (V, the solver's new array), held for the cycles it may
        stand in for, and the speed expected one period from now (m/s, ``[*pipeline_v,
        v_0, v_1][1]``): with an input delay the pipeline's prediction, the plan starting
        where its first move acts."""
        assert res.u is not None and res.v is not None
        self._plan, self._plan_age, pv = res.u, 0, self.pipeline_v
        self._v_expected = pv[1] if len(pv) > 1 else float(res.v[1 - len(pv)])

    def _update_winding(self, v: float) -> None:
        """One period of the winding's thermal model (``resistance_drift``) at the current
        measured (else the quasi-static one of the voltage applied at speed v, m/s)."""
        w = self.winding
        if w.active:
            p = self.model.params
            r = w.update(self.cfg.period, self.current, self._applied_prev(), p.omega(v))
            self._r_scale = r / p.R_m

    def _current_limited(self, wanted: float, v: float) -> float:
        """The voltage (V) the driver applies for ``wanted`` under its current limit at
        speed v (m/s), within ``u_max``; sets :attr:`_limited`."""
        u_max = self.u_max
        if not self._current_limit:  # current_window: the whole line, -inf to inf
            self._limited = math.isnan(wanted)
            c = -u_max if -u_max > wanted else wanted  # min(max(wanted, -u_max), u_max)
            return u_max if u_max < c else c
        p = self.model.params
        lo, hi = current_window(p, self.model.effects, p.omega(v), self.winding.resistance)
        self._limited = not lo <= wanted <= hi
        return min(max(wanted, lo, -u_max), hi, u_max)

    def _applied_prev(self) -> float:
        """The voltage the previous command applies at the motor (V): what it was meant to
        apply when the caller sent it unchanged, else the caller's command itself."""
        return self._wanted if self.u_prev == self._out else self.u_prev

    def _u_hi(self) -> float:
        """The highest motor voltage (V) the driver can apply now (the battery sag lowers
        it under load): the plan's real upper bound, so it never asks for more."""
        if not self._sag:
            return self.u_max
        eff, p = self.model.effects, self.model.params
        return sag_limit(self.u_max, eff.battery_sag, p.V_batt, self.current)

    def _command(self, u: float) -> float:
        """The command map: the wanted motor voltage ``u`` (V) -> the command (V) the
        driver turns into it (battery sag, then the dead zone), within ``u_max``."""
        u_max = self.u_max
        c = u
        if self._sag:
            eff, p = self.model.effects, self.model.params
            c = sag_command(u, eff.battery_sag, p.V_batt, self.current, self.vbat)
        # min(max(c, -u_max), u_max) written out (the builtins parse their arguments as a
        # keyword call: several times the comparisons' cost, every cycle)
        c = -u_max if -u_max > c else c
        c = u_max if u_max < c else c
        if self._dead_zone:
            c = self.dead_zone.command(c)
        c = -u_max if -u_max > c else c
        return u_max if u_max < c else c

    def _hold(self, est: Estimate, v: float, gap_ref: float) -> ControlOutput:
        """0 V, no MPC solve: the truck stands on stiction.  Solving would cost a QP per
        cycle whose answer is not used, and a plan of standing still is no warm start for
        the start; the first solve after the hold starts cold (and, should it fail, the
        fallback holds the last command, 0 V, instead of a stale plan)."""
        self._plan = None
        self._plan_age = 0
        self._v_expected = math.nan
        self.mpc.reset()
        return self._finish(est, v, 0.0, 0.0, "hold", None, "not-run", 0, 0.0, gap_ref)

    def _feedforward(self, v: float, x: float) -> float:
        """The feedforward voltage (V) at speed v (m/s), road position x (m): friction
        and the known loads (:mod:`truckd.control.effect_use`) plus the disturbance."""
        cfg = self.cfg
        if not cfg.feedforward:
            return self.disturbance_v
        p, eff = self.model.params, self.model.effects
        ff = moving_feedforward(p, eff, v, cfg.moving_speed, x, self._terms)
        return ff * self._r_scale + self.disturbance_v

    def _initial_state(
        self,
        v: float,
        gap: float,
        ff: float,
        v_lead: Sequence[float],
        held: bool = False,
        x_pos: float = 0.0,
    ) -> tuple[list[float], float]:
        """The QP's ``x_0`` and the feedforward (V) the plan's first command gets.

        ``x_0``: the current ``R_m i`` after the electrical transient (about 0.5 ms, so
        settled within a cycle) from the voltage acting now.  With a known input delay,
        the state predicted over the commands sent but not yet acting (a Smith-predictor-
        like forward prediction), with the lead at ``v_lead[k]`` (m/s) in pipeline step k:
        each step's friction-free input is the command less the feedforward at that step's
        speed and position (from ``x_pos``, m), and a truck that the prediction brings to
        rest stays there (friction does not drive it backwards); the feedforward returned
        is the one at the end of the pipeline, ``x_0``'s current relative to it.  Records
        :attr:`pipeline_v`."""
        p = self.model.params
        sent = self._sent
        acting = sent[0] if len(sent) == sent.maxlen else 0.0
        if self._delay_steps == 0:
            acting = self._applied_prev()
        if held:
            acting = ff  # no current beyond what the feedforward accounts for
        x0 = [acting - ff - p.K_v * (v / p.ratio), v, gap]  # K_v omega
        if self._delay_steps == 0:
            self.pipeline_v = []
            return x0, ff  # a list: the QP gathers its inputs without numpy

        def at_rest(u: float, x: float) -> float:  # stiction and the load take up to breakaway
            return max(u - breakaway_feedforward(p, self.model.effects, 1.0, x), 0.0)

        x, speeds, ff_k, x_pos = predict_pipeline(
            self.mpc.qp.pred,
            x0,
            list(sent)[1:],
            v_lead,
            ff,
            x_pos,
            self.cfg.period,
            self._feedforward,
            at_rest if self.cfg.feedforward else None,
            self.cfg.moving_speed,
        )
        self.pipeline_v = speeds[:-1]
        ff_end = self._feedforward(float(x[1]), x_pos)
        x[0] += ff_k - ff_end
        out: list[float] = x.tolist()
        return out, ff_end

    def _fallback(
        self,
        est: Estimate,
        v: float,
        reason: str,
        mode: str,
        gap_ref: float,
        status: str,
        iters: int,
        run_time: float,
        ff: float = 0.0,
    ) -> ControlOutput:
        self.fallback_cycles += 1
        self._plan_age += 1
        held = (
            None
            if reason == "speed_stale"
            else held_plan_move(self._plan, self._plan_age, self.cfg.plan_hold_steps)
        )
        if held is not None:
            move, ff_used, mode_used, tag = held, ff, mode, ":plan"
        elif (
            self._plan is None
            and reason != "speed_stale"
            and (self._plan_age <= self.cfg.plan_hold_steps)
        ):
            # No plan yet (the first, cold solve ran out of time): hold the last command.
            move, ff_used, mode_used, tag = self._applied_prev() - ff, ff, mode, ":hold"
        else:
            self.braking_cycles += 1
            ff_used, mode_used = 0.0, "fallback"
            if reason == "speed_stale":
                # No speed to brake against: braking on the last one, open loop, drives a
                # truck that has stopped backwards.  0 V (at the rate limit).
                move, tag = 0.0, ":zero"
            else:
                move, tag = braking_law(v, self.cfg.brake_gain, self.u_max), ":brake"
        return self._finish(
            est, v, move, ff_used, mode_used, reason + tag, status, iters, run_time, gap_ref
        )

    def _finish(
        self,
        est: Estimate,
        v: float,
        u_mpc: float,
        ff: float,
        mode: str,
        reason: str | None,
        status: str,
        iters: int,
        run_time: float,
        gap_ref: float,
    ) -> ControlOutput:
        cfg = self.cfg
        at_rest = abs(v) <= cfg.moving_speed
        v_act, self._v_act = self._v_act, math.nan  # speed when this command acts
        rest_act = abs(v_act) <= cfg.moving_speed if math.isfinite(v_act) else at_rest
        if cfg.feedforward and rest_act and u_mpc > cfg.start_voltage and mode != "fallback":
            ff = self._r_scale * breakaway_feedforward(
                self.model.params, self.model.effects, cfg.stiction_margin, est.x
            )
        u = u_mpc + ff
        if at_rest and u < 0.0:
            u = 0.0  # never drive backwards from rest
        wanted = limit_command(u, self._applied_prev(), self.u_max, self._du)
        # The driver's current limit: it applies K_v omega +- R I_max at most, at the
        # motor's speed as it changes within the cycle (the command is sent as wanted: a
        # command cut at the speed estimated now starves a start).  What the controller
        # records as acting (the rate limit's base, the MPC's previous input, x_0's current,
        # the delay pipeline) is the limited voltage, and the offset-free integrator stops
        # while the limit binds: no wind-up.
        acting = self._current_limited(wanted, v_act if math.isfinite(v_act) else v)
        # The known driver effects (battery sag, dead zone): the command that makes the
        # driver apply the wanted voltage, as near as it can (a dead zone may exceed the
        # rate limit by its width, never the voltage limit).
        u = self._command(wanted)
        self.u_prev = self._out = u
        self._wanted = acting
        self._sent.append(acting)
        # Positional, in the fields' order (a keyword call to a class builds a dict of
        # them, every cycle): u, u_ff, u_mpc, mode, fallback_reason, solver_status,
        # solve_iterations, solve_time_s, gap_ref, estimate, the counters.
        return ControlOutput(
            u, ff, u - ff, mode, reason, status, iters, run_time, gap_ref, est,
            self.solver_failures, self.fallback_cycles, self.overruns, self.braking_cycles,
            self.mpc.inaccurate, self.disturbance_v,
        )  # fmt: skip
