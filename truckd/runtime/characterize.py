"""``truckd characterize``: the routine that drives the truck through its bring-up checks
and the identification experiments, as one more command source of the daemon's one control
cycle (:attr:`truckd.runtime.cycle.CompanionCycle.command_source`).

The daemon runs as always (its loop, link, supervisor, recorder and telemetry); each cycle
the routine is asked for the voltage, sees the estimate and the sensor state of that cycle
and the supervisor's mode of the cycle before, and keeps:

- **bring-up checks** before anything moves far (each failure one line saying what to
  fix): link and sensors up, encoder message rate and receive errors, battery within
  limits, range reading sane and steady, free space ahead, then a short pulse (a small
  positive voltage, ramped until the truck has moved ``check_distance_m``): motor polarity,
  encoder direction and counts per metre, judged against the range sensor's view of a
  target ahead;
- **experiments** (SysId's set): a quasistatic ramp each way (slowly up, then back down to
  0 V, so the command also passes the low voltages while the truck moves: a driver's dead
  zone shows), dynamic steps each way at each level, a chirp for validation; each starts
  and ends at rest, alternately forward and back;
- **limits**: a distance budget per experiment (the configured track and the free space the
  range sensor sees ahead, less the stopping distance at ``brake_decel_m_s2``): an
  experiment that would need more is shortened, one with less than ``min_budget_m`` is not
  driven; a speed limit; a stop request (Zenoh ``truckd/<id>/stop``, SIGTERM) or a supervisor
  stop ends the routine: 0 V from the next cycle, then wait at rest.

Pure logic: no I/O and no clock (the cycle's time comes in); the CLI wires it to the daemon
(:mod:`truckd.cli.characterize`).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Any

from truckd.config.characterize import CharacterizeConfig
from truckd.control.estimator import Estimate
from truckd.control.supervisor import Decision, Mode
from truckd.runtime.sensors import SensorState

EXIT_DONE, EXIT_CHECK, EXIT_STOPPED = 0, 3, 4
"""Exit codes of ``truckd characterize`` (completed, a bring-up check failed, stopped)."""

PAUSE_S = 0.3
"""Rest between experiments (not in the experiment log: each experiment is its own run)."""


@dataclass(frozen=True)
class Check:
    """One bring-up check: ``detail`` says what was measured, or what to fix."""

    name: str
    ok: bool
    detail: str

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "detail": self.detail}


class CheckFailedError(Exception):
    """A bring-up check failed (the routine stops the truck and ends, exit 3)."""

    def __init__(self, check: Check) -> None:
        super().__init__(check.detail)
        self.check = check


@dataclass
class Experiment:
    """One experiment: its voltage profile and what happened."""

    name: str
    kind: str  # quasistatic | dynamic | validation
    direction: int  # 1 forward, -1 back, 0 both (chirp)
    duration_s: float
    level_v: float = 0.0  # ramp rate (V/s) or step / chirp amplitude (V)
    t_start: float = math.nan
    t_end: float = math.nan
    ended: str = ""  # "" duration reached | "distance budget" | "speed limit" | "stopped"
    skipped: str = ""
    distance_m: float = 0.0

    def voltage(self, tau: float, cfg: CharacterizeConfig) -> float:
        """The voltage at ``tau`` s into the experiment."""
        if self.kind == "quasistatic":  # up, then back down to 0 V at the end
            return self.direction * self.level_v * max(0.0, min(tau, self.duration_s - tau))
        if self.kind == "dynamic":
            return self.direction * self.level_v
        f0, f1, dur = cfg.validation_f0_hz, cfg.validation_f1_hz, self.duration_s
        phase = 2.0 * math.pi * (f0 * tau + 0.5 * (f1 - f0) * tau * tau / dur)
        return self.level_v * math.sin(phase)

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "t_start": _j(self.t_start),
            "t_end": _j(self.t_end),
            "ended": self.ended or "done",
            "skipped": self.skipped or None,
            "distance_m": self.distance_m,
        }


def _j(x: float) -> float | None:
    return x if math.isfinite(x) else None


def plan_experiments(cfg: CharacterizeConfig) -> list[Experiment]:
    """The experiments in order: alternately forward and back, so the truck stays near
    its start."""
    out = [
        Experiment(f"quasistatic-{name}", "quasistatic", d, cfg.quasistatic_duration_s,
                   cfg.quasistatic_ramp_v_per_s)
        for d, name in ((1, "forward"), (-1, "reverse"))
    ]  # fmt: skip
    for level in cfg.step_voltages:
        for d, name in ((1, "forward"), (-1, "reverse")):
            out.append(
                Experiment(f"dynamic-{name}-{level:g}V", "dynamic", d, cfg.step_duration_s, level)
            )
    out.append(
        Experiment("validation-chirp", "validation", 0, cfg.validation_duration_s, cfg.validation_v)
    )
    return out


@dataclass
class Obs:
    """What the routine sees in one cycle."""

    t: float
    v: float  # m/s, the estimator's (0 when it has none)
    x: float  # m, encoder distance from the start
    vbat: float
    range_m: float | None  # the last range reading (None: no target in range)
    range_t: float  # the cycle time the last range reading arrived
    encoder_msgs: int  # encoder messages this cycle
    decision: Decision  # the supervisor's, previous cycle


@dataclass
class Progress:
    """What is published on ``truckd/<id>/characterize`` and printed."""

    stage: str = "starting"
    experiment: str = ""
    percent: float = 0.0

    def as_dict(self, t: float) -> dict[str, Any]:
        return {
            "t": t,
            "stage": self.stage,
            "experiment": self.experiment,
            "percent": round(self.percent, 1),
        }


@dataclass
class Result:
    """The routine's outcome."""

    code: int = EXIT_DONE
    checks: list[Check] = field(default_factory=list)
    experiments: list[Experiment] = field(default_factory=list)
    stop_reason: str = ""
    stop_t: float = math.nan
    distance_m: float = 0.0
    duration_s: float = 0.0
    end_speed_m_s: float = math.nan


Script = Generator[float, Obs, None]


class Routine:
    """The command source (call it each cycle; see the module docstring).

    ``decision()`` is the supervisor's latest decision, ``link_stats()`` the companion
    port's counters, ``on_progress(dict)`` is called on each change of stage or experiment
    and every ``progress_period_s``, ``on_done()`` once, when the truck is at rest at the
    end (the daemon then ends its loop)."""

    def __init__(
        self,
        cfg: CharacterizeConfig,
        *,
        period: float,
        range_max: float,
        encoder_period: float,
        ticks_per_rev: int,
        r_w: float,
        decision: Callable[[], Decision],
        link_stats: Callable[[], dict[str, Any]],
        on_progress: Callable[[dict[str, Any]], None],
        on_done: Callable[[], None],
        progress_period_s: float = 0.5,
    ) -> None:
        self.cfg = cfg
        self.period = period
        self.range_max = range_max
        self.encoder_period = encoder_period
        self.ticks_per_rev = ticks_per_rev
        self.r_w = r_w
        self.decision = decision
        self.link_stats = link_stats
        self.on_progress = on_progress
        self.on_done = on_done
        self.progress_period_s = progress_period_s
        self.result = Result(experiments=plan_experiments(cfg))
        self.progress = Progress()
        self._planned = 4.0 + sum(
            e.duration_s + 2.0 * PAUSE_S + 1.0 for e in self.result.experiments
        )
        self._elapsed_plan = 0.0
        self._next_progress = 0.0
        self._stop_request = ""
        self._script: Script = self._run()
        self._primed = False
        self._finishing = False
        self.finished = False
        self._x_min = 0.0
        self._x_max = 0.0
        self._last_x: float | None = None
        self._ready = False  # link and sensors came up (the supervisor left INIT)
        self._range0: float | None = None  # the range at rest before the polarity pulse

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
        obs = yield from self._rest(obs, fail=False)
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
        obs = yield from self._wait_ready(obs)
        self._ready = True
        obs = yield from self._dwell_checks(obs)
        obs = yield from self._pulse(obs)
        self._stage("experiments", obs.t)
        for exp in self.result.experiments:
            obs = yield from self._experiment(exp, obs)
        self.result.code = EXIT_DONE

    def _fail(self, name: str, detail: str) -> CheckFailedError:
        return CheckFailedError(Check(name, False, detail))

    def _pass(self, name: str, detail: str) -> None:
        self.result.checks.append(Check(name, True, detail))

    def _wait_ready(self, obs: Obs) -> Generator[float, Obs, Obs]:
        cfg = self.cfg
        t0 = obs.t
        while obs.decision.mode not in (Mode.ACTIVE, Mode.DEGRADED):
            if obs.t - t0 > cfg.ready_timeout_s:
                raise self._not_ready(obs)
            obs = yield 0.0
        self._pass("link", f"link and sensors up after {obs.t - t0:.2f} s")
        return obs

    def _not_ready(self, obs: Obs) -> CheckFailedError:
        causes = set(obs.decision.causes)
        waited = f"{self.cfg.ready_timeout_s:g} s"
        if causes & {"link_down", "link_stale"} or not causes:
            return self._fail(
                "link",
                f"no messages from the firmware for {waited}: check the cable, the device "
                "(link: section) and that the firmware runs",
            )
        if "encoder_stale" in causes or "speed_stale" in causes:
            return self._fail(
                "encoder", f"no encoder data for {waited}: check the encoder's cable and power"
            )
        if "range_stale" in causes:
            return self._fail(
                "range",
                f"no range reading for {waited}: check the range sensor's cable and power",
            )
        if "range_fault" in causes:
            return self._fail(
                "range", "the range sensor reports a fault: check its mounting and power"
            )
        return self._fail("link", f"not ready after {waited}: {', '.join(sorted(causes))}")

    def _dwell_checks(self, obs: Obs) -> Generator[float, Obs, Obs]:
        """At rest for ``range_dwell_s``: link rate and errors, battery, range, free space."""
        cfg = self.cfg
        self._stage("checks", obs.t, "sensors")
        stats0 = self.link_stats()
        t0, msgs = obs.t, 0
        vbat: list[float] = []
        ranges: list[float | None] = []
        last_rt = obs.range_t
        cycles = 0
        while obs.t - t0 < cfg.range_dwell_s:
            obs = yield 0.0
            cycles += 1
            msgs += obs.encoder_msgs
            vbat.append(obs.vbat)
            if obs.range_t != last_rt:
                last_rt = obs.range_t
                ranges.append(obs.range_m)
        stats1 = self.link_stats()
        # link: encoder messages at the firmware's rate, no receive errors
        span = max(obs.t - t0, self.period)
        rate = msgs * self.encoder_period / span
        errors = {
            k: int(stats1.get(k, 0)) - int(stats0.get(k, 0))
            for k in stats1
            if k.startswith("rx_") and k != "rx_ok" and isinstance(stats1[k], int)
            and not isinstance(stats1[k], bool) and ("error" in k or "bad" in k or "invalid" in k)
        }  # fmt: skip
        bad = {k: n for k, n in errors.items() if n > 0}
        if rate < cfg.min_encoder_rate:
            raise self._fail(
                "link_rate",
                f"encoder messages arrive at {100 * rate:.0f} % of the firmware's rate "
                f"(1 per {self.encoder_period * 1e3:.0f} ms): check the link's baud rate and "
                "load",
            )
        if bad:
            listed = ", ".join(f"{k} {n}" for k, n in sorted(bad.items()))
            raise self._fail(
                "link_rate",
                f"receive errors at rest ({listed}): check the cable, its shielding and the "
                "baud rate",
            )
        self._pass("link_rate", f"encoder messages at {100 * rate:.0f} % of the firmware's rate")
        # battery
        vb = statistics.median(vbat) if vbat else 0.0
        if vb < cfg.battery_min_v:
            raise self._fail(
                "battery",
                f"battery {vb:.2f} V is below {cfg.battery_min_v:g} V "
                "(characterize.battery_min_v): charge or swap the battery",
            )
        if vb > cfg.battery_max_v:
            raise self._fail(
                "battery",
                f"battery {vb:.2f} V is above {cfg.battery_max_v:g} V "
                "(characterize.battery_max_v): check the battery type and the voltage sense",
            )
        self._pass("battery", f"{vb:.2f} V at rest")
        # range: sane and steady
        valid = [r for r in ranges if r is not None]
        if not ranges:
            raise self._fail(
                "range",
                f"no range reading in {cfg.range_dwell_s:g} s at rest: check the range "
                "sensor's cable and power",
            )
        if valid and len(valid) < len(ranges):
            raise self._fail(
                "range",
                f"the range sensor loses its target at rest ({len(ranges) - len(valid)} of "
                f"{len(ranges)} readings): check its mounting and what is ahead",
            )
        spread = statistics.pstdev(valid) if len(valid) > 1 else 0.0
        if spread > cfg.range_steady_std_m:
            raise self._fail(
                "range",
                f"the range reading spreads {spread:.3f} m at rest (limit "
                f"{cfg.range_steady_std_m:g} m, characterize.range_steady_std_m): check the "
                "sensor's mounting and that nothing moves ahead",
            )
        ahead = statistics.median(valid) if valid else None
        self._range0 = ahead
        self._pass(
            "range",
            f"{ahead:.3f} m ahead, spread {spread:.4f} m"
            if ahead is not None
            else f"no target within {self.range_max:g} m",
        )
        free = self._free_ahead(obs)
        if free < cfg.min_budget_m:
            what = f"a target {ahead:.2f} m ahead" if ahead is not None else "the track"
            raise self._fail(
                "free_space",
                f"{what} leaves {max(free, 0.0):.2f} m to drive, less than the "
                f"{cfg.min_budget_m:g} m an experiment needs (characterize.min_budget_m, "
                f"wall_margin_m {cfg.wall_margin_m:g} m): move the truck back or clear the "
                "track",
            )
        self._pass("free_space", f"{free:.2f} m to drive ahead")
        return obs

    def _free_ahead(self, obs: Obs) -> float:
        """Distance the truck may still drive forward (m): the track, and what the range
        sensor sees ahead less the margin (nothing seen: free up to its maximum)."""
        cfg = self.cfg
        track = cfg.track_length_m - obs.x
        seen = (obs.range_m if obs.range_m is not None else self.range_max) - cfg.wall_margin_m
        return min(track, seen)

    def _free_behind(self, obs: Obs) -> float:
        return self.cfg.track_length_m + obs.x

    def _settled_range(
        self, obs: Obs, dwell: float
    ) -> Generator[float, Obs, tuple[Obs, float | None]]:
        """At rest for ``dwell`` s: the median range reading (None: no target)."""
        t0, vals = obs.t, []
        last = obs.range_t
        while obs.t - t0 < dwell:
            obs = yield 0.0
            if obs.range_t != last:
                last = obs.range_t
                vals.append(obs.range_m)
        got = [r for r in vals if r is not None]
        return obs, (statistics.median(got) if got and len(got) == len(vals) else None)

    def _pulse(self, obs: Obs) -> Generator[float, Obs, Obs]:
        """A small positive voltage, ramped until the truck moved: polarity, encoder
        direction, counts per metre."""
        cfg = self.cfg
        self._stage("checks", obs.t, "polarity")
        r0, x0, t0 = self._range0, obs.x, obs.t
        u = 0.0
        held = 0.0
        while True:
            moved = abs(obs.x - x0)
            seen = abs(obs.range_m - r0) if (r0 is not None and obs.range_m is not None) else 0.0
            if max(moved, seen) >= cfg.check_distance_m:
                break
            if abs(obs.v) > cfg.speed_limit_m_s:
                break
            if u >= cfg.check_max_v:
                held += self.period
                if held > 0.5:
                    break
            u = min(cfg.check_max_v, cfg.check_ramp_v_per_s * (obs.t - t0))
            obs = yield u
        obs = yield from self._rest(obs)
        obs, r1 = yield from self._settled_range(obs, 0.3)
        dx = obs.x - x0
        dr = (r0 - r1) if (r0 is not None and r1 is not None) else None  # > 0: forward
        small = 0.25 * cfg.check_distance_m
        if abs(dx) < small and (dr is None or abs(dr) < small):
            raise self._fail(
                "motor_polarity",
                f"the truck did not move with up to {cfg.check_max_v:g} V: check the motor's "
                "cable, the driver and that the wheels are free",
            )
        if dr is not None and abs(dr) >= small:
            if dr < 0:
                raise self._fail(
                    "motor_polarity",
                    f"a positive voltage drove the truck backwards (the target ahead moved "
                    f"{-dr:.3f} m away): swap the motor leads",
                )
            self._pass("motor_polarity", f"forward under +V ({dr:.3f} m by the range sensor)")
            if abs(dx) < small:
                raise self._fail(
                    "encoder_direction",
                    f"the truck drove {dr:.3f} m but the encoder counted {dx:.3f} m: check "
                    "the encoder's cable and power",
                )
            if dx < 0:
                raise self._fail(
                    "encoder_direction",
                    f"the encoder counts down while the truck drives forward ({dx:.3f} m by "
                    f"the encoder, {dr:.3f} m by the range sensor): swap the encoder's A and B "
                    "channels",
                )
            self._pass("encoder_direction", f"counts up going forward ({dx:.3f} m)")
            ratio = dx / dr
            tol = cfg.counts_tolerance
            per_m = self.ticks_per_rev / (2.0 * math.pi * self.r_w)
            if not 1.0 - tol <= ratio <= 1.0 + tol:
                raise self._fail(
                    "counts_per_metre",
                    f"the encoder says {dx:.3f} m where the range sensor says {dr:.3f} m "
                    f"({ratio:.2f}x): the configured {per_m:.0f} counts/m (link."
                    f"encoder_ticks_per_rev {self.ticks_per_rev}, vehicle.r_w {self.r_w:g} m) "
                    f"are off: configure {per_m * ratio:.0f} counts/m",
                )
            self._pass("counts_per_metre", f"encoder/range distance ratio {ratio:.3f}")
            return obs
        if dx < 0:
            raise self._fail(
                "motor_polarity",
                "the encoder counts down under a positive voltage: the motor leads or the "
                f"encoder channels are swapped; put a target within {self.range_max:g} m "
                "ahead so the range sensor can tell which, and rerun",
            )
        self._pass("motor_polarity", f"encoder counts up under +V ({dx:.3f} m)")
        self._pass("encoder_direction", "not checked apart from the motor: no target ahead")
        self._pass("counts_per_metre", "not checked: no target ahead of the range sensor")
        return obs

    def _rest(self, obs: Obs, fail: bool = True) -> Generator[float, Obs, Obs]:
        """0 V until at rest (slower than ``rest_speed_m_s`` for 0.2 s)."""
        cfg = self.cfg
        t0, calm = obs.t, 0.0
        while calm < 0.2:
            obs = yield 0.0
            calm = calm + self.period if abs(obs.v) < cfg.rest_speed_m_s else 0.0
            if obs.t - t0 > cfg.rest_timeout_s:
                if fail:
                    raise self._fail(
                        "rest",
                        f"the truck still moves at {obs.v:.2f} m/s {cfg.rest_timeout_s:g} s "
                        "after 0 V: check the driver and the brake",
                    )
                break
        return obs

    def _experiment(self, exp: Experiment, obs: Obs) -> Generator[float, Obs, Obs]:
        cfg = self.cfg
        self._stage("experiments", obs.t, exp.name)
        ahead, behind = self._free_ahead(obs), self._free_behind(obs)
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
            room = self._free_ahead(obs) if v > 0 else self._free_behind(obs)
            if room <= stop_dist + 0.02:
                exp.ended = "distance budget"
                break
            if abs(v) > cfg.speed_limit_m_s:
                exp.ended = "speed limit"
                break
            obs = yield exp.voltage(tau, cfg)
            dist += abs(obs.x - last_x)
            last_x = obs.x
        obs = yield from self._rest(obs)
        exp.t_end = obs.t
        exp.distance_m = round(dist + abs(obs.x - last_x), 4)
        t_pause = obs.t
        while obs.t - t_pause < PAUSE_S:
            obs = yield 0.0
        return obs
