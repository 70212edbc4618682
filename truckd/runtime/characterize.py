"""``truckd characterize``: the routine that drives the truck through its bring-up checks
and the identification experiments, as one more command source of the daemon's one control
cycle (:attr:`truckd.runtime.cycle.CompanionCycle.command_source`).

The daemon runs as always (its loop, link, supervisor, recorder and telemetry); each cycle
the routine is asked for the voltage, sees the estimate and the sensor state of that cycle
and the supervisor's mode of the cycle before, and runs, in order:

- the **bring-up checks** (:mod:`truckd.runtime.characterize_checks`), before anything
  moves far;
- the **experiments** (:mod:`truckd.runtime.characterize_plan`: SysId's set, a
  quasistatic ramp each way, dynamic steps each way at each level, a chirp for
  validation), each from rest to rest, alternately forward and back;
- the **limits**, every cycle: a distance budget per experiment (the configured track and
  the free space the range sensor sees ahead, less the stopping distance at
  ``brake_decel_m_s2``): an experiment that would need more is shortened, one with less
  than ``min_budget_m`` is not driven; a speed limit; a stop request (Zenoh
  ``truckd/<id>/stop``, SIGTERM) or a supervisor stop ends the routine: 0 V from the next
  cycle, then wait at rest.

It publishes its progress and ends with a :class:`Result`.  Pure logic: no I/O and no
clock (the cycle's time comes in); the CLI wires it to the daemon
(:mod:`truckd.cli.characterize`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from typing import Any

from truckd.config.characterize import CharacterizeConfig
from truckd.control.estimator import Estimate
from truckd.control.supervisor import Decision, Mode
from truckd.runtime.characterize_checks import BringUp, free_ahead, free_behind, rest
from truckd.runtime.characterize_plan import (
    EXIT_CHECK,
    EXIT_DONE,
    EXIT_STOPPED,
    PAUSE_S,
    CheckFailedError,
    Experiment,
    Obs,
    Progress,
    Result,
    Script,
    TruckFacts,
    plan_experiments,
)
from truckd.runtime.sensors import SensorState


class Routine:
    """The command source (call it each cycle; see the module docstring).

    ``decision()`` is the supervisor's latest decision, ``link_stats()`` the companion
    port's counters, ``on_progress(dict)`` is called on each change of stage or experiment
    and every ``progress_period_s``, ``on_done()`` once, when the truck is at rest at the
    end (the daemon then ends its loop)."""

    def __init__(
        self,
        cfg: CharacterizeConfig,
        truck: TruckFacts,
        *,
        decision: Callable[[], Decision],
        link_stats: Callable[[], dict[str, Any]],
        on_progress: Callable[[dict[str, Any]], None],
        on_done: Callable[[], None],
        progress_period_s: float = 0.5,
    ) -> None:
        self.cfg = cfg
        self.period = truck.period
        self.range_max = truck.range_max
        self.decision = decision
        self.on_progress = on_progress
        self.on_done = on_done
        self.progress_period_s = progress_period_s
        self.result = Result(experiments=plan_experiments(cfg))
        self.progress = Progress()
        self._planned = 4.0 + sum(
            e.duration_s + 2.0 * PAUSE_S + 1.0 for e in self.result.experiments
        )
        self._next_progress = 0.0
        self._stop_request = ""
        self._script: Script = self._run()
        self._primed = False
        self._finishing = False
        self.finished = False
        self._last_x: float | None = None
        self._ready = False  # link and sensors came up (the supervisor left INIT)
        self.bringup = BringUp(
            cfg, truck, link_stats=link_stats, checks=self.result.checks, stage=self._stage
        )

    # -- the command source ----------------------------------------------------------------
    def request_stop(self, reason: str) -> None:
        """Stop (any thread): 0 V from the next cycle, then wait at rest, then end."""
        if not self._stop_request:
            self._stop_request = reason

    def __call__(self, t: float, est: Estimate, sensors: SensorState) -> float:
        v = est.v if est.speed_valid and math.isfinite(est.v) else 0.0
        obs = Obs(
            t=t, v=v, x=sensors.x, vbat=sensors.vbat,
            range_m=sensors.range_raw if sensors.range_valid else None,
            range_t=sensors.t_range, encoder_msgs=len(sensors.encoders),
            decision=self.decision(),
        )  # fmt: skip
        if self._last_x is not None:
            self.result.distance_m += abs(obs.x - self._last_x)
        self._last_x = obs.x
        if self.finished:
            return 0.0
        if not self._finishing:
            reason = self._stop_request or self._supervisor_stop(obs)
            if reason:
                self._stop(obs, reason)
        try:
            if not self._primed:
                self._primed = True
                u = next(self._script)
            else:
                u = self._script.send(obs)
        except CheckFailedError as exc:
            self.result.checks.append(exc.check)
            self.result.code = EXIT_CHECK
            self._stage("check failed", obs.t)
            return self._finish(obs)
        except StopIteration:
            self.finished = True
            self.result.duration_s = obs.t
            self.result.end_speed_m_s = obs.v
            self._stage("done" if self.result.code == EXIT_DONE else "stopped", obs.t)
            self.on_done()
            return 0.0
        if obs.t >= self._next_progress:
            self._publish(obs.t)
        return u

    def _supervisor_stop(self, obs: Obs) -> str:
        d = obs.decision
        driving = self.progress.stage in ("checks", "experiments") and self._ready
        if driving and d.mode in (Mode.SAFE_STOP, Mode.FAULT):
            return f"supervisor {d.mode.value}: {', '.join(d.causes)}"
        return ""

    def _stop(self, obs: Obs, reason: str) -> None:
        self.result.code = EXIT_STOPPED
        self.result.stop_reason = reason
        self.result.stop_t = obs.t
        for e in self.result.experiments:
            if math.isfinite(e.t_start) and not math.isfinite(e.t_end):
                e.ended = "stopped"
        self._stage("stopping", obs.t)
        self._finish(obs)

    def _finish(self, obs: Obs) -> float:
        """Switch to the end: 0 V until at rest (the open experiment ends there)."""
        self._finishing = True
        self._script.close()
        self._script = self._end()
        self._primed = False
        return 0.0

    def _end(self) -> Script:
        obs = yield 0.0
        obs = yield from rest(obs, self.cfg, self.period, fail=False)
        for e in self.result.experiments:
            if math.isfinite(e.t_start) and not math.isfinite(e.t_end):
                e.t_end = obs.t
                e.distance_m = round(e.distance_m, 4)

    def _stage(self, stage: str, t: float, experiment: str = "") -> None:
        self.progress.stage, self.progress.experiment = stage, experiment
        self._publish(t)

    def _publish(self, t: float) -> None:
        done = self.progress.stage in ("done", "analysis")
        self.progress.percent = 100.0 if done else min(99.0, 100.0 * t / self._planned)
        self._next_progress = t + self.progress_period_s
        self.on_progress(self.progress.as_dict(t))

    # -- the script ----------------------------------------------------------------------
    def _run(self) -> Script:
        obs = yield 0.0
        self._stage("checks", obs.t, "link")
        obs = yield from self.bringup.wait_ready(obs)
        self._ready = True
        obs = yield from self.bringup.dwell_checks(obs)
        obs = yield from self.bringup.pulse(obs)
        self._stage("experiments", obs.t)
        for exp in self.result.experiments:
            obs = yield from self._experiment(exp, obs)
        self.result.code = EXIT_DONE

    def _experiment(self, exp: Experiment, obs: Obs) -> Generator[float, Obs, Obs]:
        cfg = self.cfg
        self._stage("experiments", obs.t, exp.name)
        ahead, behind = free_ahead(obs, cfg, self.range_max), free_behind(obs, cfg)
        need = {1: ahead, -1: behind, 0: min(ahead, behind)}[exp.direction]
        if need < cfg.min_budget_m:
            exp.skipped = f"{need:.2f} m free, {cfg.min_budget_m:g} m needed"
            return obs
        exp.t_start = obs.t
        last_x, dist = obs.x, 0.0
        while True:
            tau = obs.t - exp.t_start
            if tau >= exp.duration_s:
                break
            v = obs.v
            stop_dist = v * v / (2.0 * cfg.brake_decel_m_s2) + abs(v) * 3.0 * self.period
            room = free_ahead(obs, cfg, self.range_max) if v > 0 else free_behind(obs, cfg)
            if room <= stop_dist + 0.02:
                exp.ended = "distance budget"
                break
            if abs(v) > cfg.speed_limit_m_s:
                exp.ended = "speed limit"
                break
            obs = yield exp.voltage(tau, cfg)
            dist += abs(obs.x - last_x)
            last_x = obs.x
        obs = yield from rest(obs, cfg, self.period)
        exp.t_end = obs.t
        exp.distance_m = round(dist + abs(obs.x - last_x), 4)
        t_pause = obs.t
        while obs.t - t_pause < PAUSE_S:
            obs = yield 0.0
        return obs
