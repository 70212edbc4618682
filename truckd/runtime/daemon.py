"""``truckd run``: the daemon's wiring.

Each cycle, on the rate keeper's absolute deadlines:
read (checked messages) -> estimate + control (the pure Controller) -> supervise (mode)
-> command (always finite, within limits) -> publish (Zenoh, non-blocking) -> record
(CSV, non-blocking) -> watchdog -> keep rate.

SIGTERM, SIGINT and SIGHUP (unless ignored at start, as under ``nohup``) end the loop at
the next cycle: the motor is commanded off, the logs flushed and closed (the MCAP with
its index), the link closed, and ``run`` returns 0.  At start, MCAP files a crash left
unfinished in the log directory are recovered (:mod:`truckd.runtime.mcap_recover`).
"""

from __future__ import annotations

import logging
import math
import os
import signal
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from firmware_protocol.messages import CompanionHeartbeat, CompanionState, MotorCommand
from truckd.config.truck import TruckConfig
from truckd.control.output import ControlOutput
from truckd.control.platoon import PlatoonDecision, platoon_control
from truckd.control.qp import ControlModel
from truckd.control.supervisor import Decision, Mode
from truckd.io.devlock import DeviceLock
from truckd.io.port import Port, companion_port
from truckd.jsonsafe import json_number
from truckd.runtime.backend import Backend, claim_backend, open_backend
from truckd.runtime.cycle import LOG_COLUMNS as STEP_COLUMNS
from truckd.runtime.cycle import MODE_CODE as MODE_CODE
from truckd.runtime.cycle import CompanionCycle, CycleInputs, CycleOutputs, state_message
from truckd.runtime.deferred import Deferred
from truckd.runtime.faults import RuntimeFaults, wrap_solver
from truckd.runtime.mcap_log import McapLog
from truckd.runtime.mcap_recover import recover_dir
from truckd.runtime.notify import Notifier
from truckd.runtime.platoon_link import DaemonPlatoon, platoon_state_fields
from truckd.runtime.ratekeeper import RateKeeper
from truckd.runtime.realtime import (
    RealtimeReport,
    promote_helpers,
    release_cpu_latency,
    setup_realtime,
    unfreeze_gc,
)
from truckd.runtime.recorder import Recorder
from truckd.runtime.rxlog import RxLog
from truckd.runtime.telemetry import Telemetry
from truckd.schema import to_plain

log = logging.getLogger("truckd.daemon")

LOG_COLUMNS = (*STEP_COLUMNS, "lateness_us", "compute_us", "cpu_us")
"""Recorded columns: the step's (contract names first, reference section 3), then the
loop's timing (us): this cycle's wake-up lateness, the previous cycle's wall-clock compute
time and the CPU time the loop thread used in it (``time.thread_time``).  Compute minus
CPU is time the loop waited for the host (descheduled, the GIL, blocking I/O): the host's
stall as the OS accounts it, as opposed to the code's own work."""


def _state_message(
    out: CycleOutputs, lateness_s: float, platoon: PlatoonDecision | None
) -> dict[str, Any]:
    """The state message (reference section 5) of the cycle ``out``, with the platoon's
    fields of that cycle's decision (all frozen: built later, on another thread)."""
    return {**state_message(out, lateness_s), **platoon_state_fields(platoon)}


class Daemon:
    """The control loop and everything around it (see module docstring)."""

    def __init__(
        self,
        cfg: TruckConfig,
        backend: str | None = None,
        *,
        duration: float | None = None,
        model: ControlModel | None = None,
        env: Mapping[str, str] | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.cfg = cfg
        self.rt = cfg.runtime
        self.control_cfg = platoon_control(cfg.control, cfg.platoon)
        self.backend_name = backend or self.rt.backend
        self.duration = duration
        self.clock = clock
        self.ticks_per_rev = cfg.ticks_per_rev
        self.model = model if model is not None else ControlModel(cfg.vehicle)
        self.companion = CompanionCycle(
            self.model,
            self.control_cfg,
            self.rt.supervisor,
            self.ticks_per_rev,
            self.rt.stop_ramp_v_per_s,
            time_budget=True,  # on the car a late solve is a failure
            stall_limit_s=self.rt.stall_limit_s,
        )
        self.controller = self.companion.controller
        self.platoon = DaemonPlatoon(cfg.vehicle_id, cfg.platoon, self.companion)
        self._last_cycle: CycleOutputs | None = None
        self.supervisor = self.companion.supervisor
        self.sensors = self.companion.sensors
        self.faults = RuntimeFaults()
        if self.rt.fault_injection:
            self.controller.mpc.solve = wrap_solver(  # type: ignore[method-assign]
                self.controller.mpc.solve, self.faults
            )
        self.rk = RateKeeper(self.control_cfg.rate_hz, clock=clock, sleep=sleep)
        self.notifier = Notifier(env)
        self.u_max = self.companion.u_max
        self.period = 1.0 / self.control_cfg.rate_hz
        self.claim: DeviceLock | None = None
        self.backend: Backend | None = None
        self.port: Port | None = None
        self.telemetry: Telemetry | None = None
        self.recorder: Recorder | None = None
        self.mcap: McapLog | None = None  # MCAP beside the CSV (recorder.mcap)
        self.rxlog: RxLog | None = None
        self.realtime = RealtimeReport()
        self.stop_requested = False
        self.t0 = 0.0
        self.last_cpu = 0.0  # s of CPU the loop thread used in the last cycle
        self.seq = 0
        self.u = 0.0
        self.enable = False
        self.decision = Decision(Mode.INIT, ())
        self.out: ControlOutput | None = None
        self.ready_sent = False
        self._last_watchdog = -math.inf
        self._next_health = 0.0
        self._states_sent = 0
        self._rate_mark = (0.0, 0)
        self._transitions: list[dict[str, object]] = []
        self._last_stall_t: float | None = None

    # -- start-up and shutdown -----------------------------------------------------
    def params(self) -> dict[str, Any]:
        """The parameters in use (answer of the ``params`` queryable)."""
        return {
            "vehicle_id": self.cfg.vehicle_id,
            "vehicle": to_plain(self.cfg.vehicle),
            "model": {
                "vehicle": to_plain(self.model.params),
                "effects": to_plain(self.model.effects),
            },
            "control": to_plain(self.control_cfg),
            "link": to_plain(self.cfg.link),
            "runtime": to_plain(self.rt),
            "backend": self.backend_name,
            "ticks_per_rev": self.ticks_per_rev,
        }

    def start(self) -> None:
        """Claim the device, open telemetry and the recorder, then the link (raises
        TruckdError/InputError).  The device is locked before anything opens it and the
        link is opened last, so a daemon that fails to start never touched the device."""
        self.claim = claim_backend(self.backend_name, self.cfg.link)
        if self.rt.telemetry.enabled:
            self.telemetry = Telemetry(self.cfg.vehicle_id, self.rt.telemetry, self.params)
            self.platoon.limit_ingress(self.telemetry.limit_ingress)
            self.telemetry.start()
            self.platoon.subscribe(
                self.telemetry.subscribe_key,
                self.rt.fault_injection,
                self.telemetry.subscribe_raw,
                self.telemetry.subscribe_keyed,
            )
            if self.rt.fault_injection:
                self.telemetry.subscribe("inject", self.faults.apply)
        if self.rt.recorder.enabled:
            self._recover_logs()
            self.mcap = McapLog.for_recorder(self.cfg.vehicle_id, self.rt.recorder)
            if self.rt.recorder.messages:  # for replay, rotated with the CSV
                self.rxlog = RxLog(self.params(), keep=self.rt.recorder.keep)
            self.recorder = Recorder(
                self.rt.recorder, LOG_COLUMNS, sidecar=self.mcap, sidecars=(self.rxlog,)
            )
            self.recorder.start()
            log.info("recording to %s", self.recorder.path)
        self.backend = open_backend(
            self.backend_name, self.cfg, self.control_cfg, self.clock, lock=self.claim
        )  # fmt: skip
        self.port = companion_port(self.backend.link, self.clock, self.cfg.link.timeout_periods)
        log.info(
            "truckd %s: backend %s, %.0f Hz, numerics %s", self.cfg.vehicle_id,
            self.backend_name, self.control_cfg.rate_hz, self.controller.backend,
        )  # fmt: skip

    def _recover_logs(self) -> None:
        """Finish the MCAP files a crash left unfinished in the log directory (index and
        footer rewritten; files another running daemon writes are left alone)."""
        d = Path(self.rt.recorder.dir)
        if not d.is_dir():
            return
        for r in recover_dir(d):
            if r.status == "recovered":
                log.warning("%s", r.line())

    def request_stop(self, signum: int = 0, _frame: object = None) -> None:
        """Signal handler: finish the current cycle, then shut down."""
        self.stop_requested = True

    def shutdown(self) -> None:
        """Motor off, notify, flush the log, close telemetry and the link.

        Motor-off goes out only on a link this daemon opened (``port`` is set only then,
        under the device lock): a daemon that failed to start sends nothing.  Each step is
        guarded: one that fails is logged and the rest still run, and the link is closed and
        the device released whatever happened before."""
        self.notifier.stopping("stopping: motor off")
        try:
            for step in (self._motor_off, self._close_logs, self._close_telemetry):
                try:
                    step()
                except Exception:  # keep shutting down: the lock must be released
                    log.exception("shutdown step %s failed", step.__name__)
        finally:
            try:
                if self.backend is not None:
                    self.backend.close()
            finally:
                if self.claim is not None:
                    self.claim.release()
                release_cpu_latency()
                # the collector as before start-up: a daemon run in-process (characterize's
                # analysis after its drive, tests) leaves no start-up object uncollectable
                unfreeze_gc()
                self.notifier.close()
        s = self.rk.stats()
        log.info(
            "stopped after %d cycles: misses %d, lateness p99 %.0f us, compute p99 %.0f us",
            s.cycles, s.misses, s.lateness_us_p99, s.compute_us_p99,
        )  # fmt: skip

    def _motor_off(self) -> None:
        if self.port is not None:
            for _ in range(3):
                try:
                    self.port.send(MotorCommand(0.0, False))
                    self.port.send(CompanionHeartbeat(CompanionState.INIT, 0))
                except Exception as exc:  # the link may be gone: nothing more to do
                    log.warning("could not send motor off: %s", exc)
                    break
        if self.backend is not None:
            self.backend.tick(self.period)  # sim: let the firmware apply it

    def _close_logs(self) -> None:
        if self.telemetry is not None or self.mcap is not None:
            self.publish_health(self.clock() - self.t0)  # the last health, also into the MCAP
        if self.recorder is not None and self.port is None:
            self.recorder.discard()  # did not start: no empty log left behind
        elif self.recorder is not None:
            self.recorder.stop()
            if self.recorder.errors:  # a full disk or a size limit: say so, never "flushed"
                log.error(
                    "log incomplete: %d write errors; %s holds the rows written before "
                    "the first failure", self.recorder.errors, self.recorder.path,
                )  # fmt: skip
            else:
                log.info("log flushed: %d rows in %s", self.recorder.rows, self.recorder.path)

    def _close_telemetry(self) -> None:
        if self.telemetry is not None:
            self.telemetry.close()

    def run(self) -> int:
        """Start, loop until SIGTERM/SIGINT/SIGHUP or the duration, shut down; exit code 0.

        SIGHUP (the terminal hung up) stops like SIGTERM, unless it is ignored when the
        daemon starts (``nohup``): an ignored SIGHUP stays ignored.  systemd sends none
        (the unit has no ``SendSIGHUP=`` and no reload)."""
        sigs = [signal.SIGTERM, signal.SIGINT]
        if signal.getsignal(signal.SIGHUP) is not signal.SIG_IGN:
            sigs.append(signal.SIGHUP)
        old = {s: signal.signal(s, self.request_stop) for s in sigs}
        try:
            self.start()
            self.realtime = setup_realtime(
                self.rt.realtime, self.rt.rt_priority, self.rt.cpu_latency_us
            )
            if self.realtime.sched_fifo:
                promote_helpers(max(1, self.rt.rt_priority - 1), self.realtime)
            self.loop()
        finally:
            self.shutdown()
            for s, h in old.items():
                signal.signal(s, h)
        return 0

    def loop(self) -> None:
        """Cycles until stopped."""
        self.rk.start()
        self.t0 = self.companion.t0 = self.rk.cycle_start
        if self.rxlog is not None:
            self.rxlog.t0 = self.t0
        while not self.stop_requested:
            if self.duration is not None and self.clock() - self.t0 >= self.duration:
                break
            self.rk.begin_cycle()
            cpu0 = time.thread_time()
            self.cycle()
            if self.faults.overrun_s > 0:
                time.sleep(self.faults.overrun_s)
            self.last_cpu = time.thread_time() - cpu0
            self.rk.keep_time()

    # -- one cycle -----------------------------------------------------------------
    def cycle(self) -> None:
        """read -> the companion step (sensors, control, supervise, command) -> send ->
        publish -> record -> watchdog."""
        assert self.port is not None and self.backend is not None
        now = self.clock()
        try:
            received = self.port.poll()
        except Exception as exc:  # a link bug must not stop the loop: treat as silence
            log.warning("link read failed: %s", exc)
            received = []
        pl = self.platoon.decide(self._last_cycle)
        inp = CycleInputs(
            now,
            received,
            self.backend.link.connected,
            self.rk.last_missed,
            lead_forecast=pl.forecast if pl is not None else None,
            headway=pl.headway if pl is not None else None,
        )
        out = self.companion.step(inp)
        if self.rxlog is not None:
            self.rxlog.record(inp, out)
        self.after_step(out)
        self.send_command(out)
        self.backend.tick(self.period)
        self.publish(out)
        self.record(out)
        self.feed_watchdog(now)

    def after_step(self, out: CycleOutputs) -> None:
        """The daemon's view of the step: log errors and mode changes, notify systemd."""
        self.out, self.decision = out.control, out.decision
        self._last_cycle = out
        self.u, self.enable, self.seq = out.command.voltage, out.command.enable, out.seq + 1
        if out.stall_s > 0.0:
            log.warning(
                "loop stalled for %.3f s (limit %.3f s) at t=%.3f s: estimator and controller "
                "re-initialised, motor off until the sensors are fresh",
                out.stall_s, self.rt.stall_limit_s, out.t,
            )  # fmt: skip
            self._last_stall_t = out.t
            self._next_health = 0.0  # publish health now
        if out.error is not None and self.companion.controller_errors <= 3:
            log.error("controller failed: %s", out.error)
        tr = out.decision.transition
        if tr is not None:
            # Into ACTIVE with nothing wrong (the start, a recovery) is news, not a warning.
            level = logging.INFO if tr.new == Mode.ACTIVE and not tr.causes else logging.WARNING
            log.log(
                level, "mode %s -> %s at t=%.3f s (%s)", tr.old.value, tr.new.value, out.t,
                ", ".join(tr.causes) or "all clear",
            )  # fmt: skip
            self._transitions = [*self._transitions[-9:], tr.as_dict()]
            if not self.ready_sent and tr.old == Mode.INIT:
                self.notifier.ready("link and sensors up")
                self.ready_sent = True
            self.notifier.status(f"{tr.new.value}: {', '.join(tr.causes) or 'ok'}")
            self._next_health = 0.0  # publish health now

    @property
    def controller_errors(self) -> int:
        return self.companion.controller_errors

    def send_command(self, out: CycleOutputs) -> None:
        assert self.port is not None
        try:
            self.port.send(out.command)
            if out.heartbeat is not None:  # 100 ms
                self.port.send(out.heartbeat)
        except Exception as exc:  # a vanished device is the supervisor's business
            log.debug("send failed: %s", exc)

    def feed_watchdog(self, now: float) -> None:
        """WATCHDOG=1 only while the loop meets its deadlines and the link is fresh."""
        wd = self.notifier.watchdog_usec * 1e-6
        if wd <= 0 or not self.ready_sent or now - self._last_watchdog < wd / 4:
            return
        link_fresh = self.sensors.ages(now)["link"] <= self.rt.supervisor.link_timeout_s
        if link_fresh and not self.rk.last_missed:
            self.notifier.watchdog()
            self._last_watchdog = now

    # -- outputs -------------------------------------------------------------------
    def publish(self, out: CycleOutputs) -> None:
        tel, mc = self.telemetry, self.mcap
        if tel is None and mc is None:
            return
        to_tel = tel is not None and out.seq % self.rt.telemetry.state_every == 0
        to_mcap = mc is not None and mc.wants_state(out.seq)
        if to_tel or to_mcap:
            # Built on the publisher or the recorder thread, whichever needs it first: the
            # loop's cycle only hands over its frozen outputs (docs/daemon.md, "Performance").
            msg = Deferred(_state_message, out, self.rk.last_lateness, self.platoon.decision)
            if mc is not None and to_mcap:
                mc.record_state(out.t, msg)
            if tel is not None and to_tel:
                tel.publish_state(msg)
                self._states_sent += 1
        plan = self.platoon.plan_message(out)
        if plan is not None:
            if tel is not None:
                tel.publish_plan(plan)
            if mc is not None:
                mc.record_plan(out.t, plan)
        if out.t >= self._next_health:
            self.publish_health(out.t)
            self._next_health = out.t + self.rt.telemetry.health_period_s

    def publish_health(self, t: float) -> None:
        tel, port = self.telemetry, self.port
        if tel is None and self.mcap is None:
            return
        t_mark, n_mark = self._rate_mark
        rate = (self._states_sent - n_mark) / (t - t_mark) if t - t_mark > 0.2 else None
        if t - t_mark > 0.2:
            self._rate_mark = (t, self._states_sent)
        ages = self.sensors.ages(self.clock())
        out = self.out
        rk = self.rk
        msg: dict[str, Any] = {
            "t": t,
            "mode": self.decision.mode.value,
            "faults": list(self.decision.causes),
            "transitions": list(self._transitions),
            "ages_s": {k: json_number(v) for k, v in ages.items()},
            "link": port.stats() if port is not None else {},
            "firmware": {
                "state": self.sensors.fw_state.name,
                "faults": int(self.sensors.fw_faults),
                "invalid_messages": self.sensors.invalid,
                "repeated_samples": self.sensors.repeated,
                "range_faults": self.sensors.range_faults,
            },
            "controller": {
                "solver_failures": out.solver_failures if out is not None else None,
                "fallback_cycles": out.fallback_cycles if out is not None else None,
                "braking_cycles": out.braking_cycles if out is not None else None,
                "errors": self.controller_errors,
                "mpc_backend": self.controller.mpc.backend,
                "numerics_backend": self.controller.backend,
            },
            "telemetry": {"dropped": tel.dropped, "sent": tel.sent, "errors": tel.errors}
            if tel is not None
            else None,
            "recorder": self._recorder_health(),
            "realtime": self.realtime.as_dict(),
            "state_rate_hz": rate,
            "injected": {"solver": self.faults.solver_fail, "overrun_s": self.faults.overrun_s},
            "stall": {
                "count": self.companion.stalls,
                "last_s": self.companion.last_stall_s if self.companion.stalls else None,
                "last_t": self._last_stall_t,
                "limit_s": self.rt.stall_limit_s,
            },
            "pid": os.getpid(),
            "platoon": self.platoon.health(),
        }
        extra = lambda: {"loop": rk.stats().as_dict()}  # noqa: E731
        if self.mcap is not None:
            self.mcap.record_health(t, msg, extra)
        if tel is not None:
            tel.publish_health(msg, extra)

    def _recorder_health(self) -> dict[str, Any] | None:
        r = self.recorder
        if r is None:
            return None
        d = {"rows": r.rows, "dropped": r.dropped, "errors": r.errors, "file": str(r.path)}
        return d if self.mcap is None else {**d, "mcap": self.mcap.health()}

    def record(self, out: CycleOutputs) -> None:
        rec = self.recorder
        if rec is None:
            return
        rk = self.rk
        rec.record(
            (
                *self.companion.log_row(out),
                rk.last_lateness * 1e6,
                rk.last_compute * 1e6,
                self.last_cpu * 1e6,
            )
        )
