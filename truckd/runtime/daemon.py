"""``truckd run``: the daemon's wiring.

Each cycle, on the rate keeper's absolute deadlines:
read (checked messages) -> estimate + control (the pure Controller) -> supervise (mode)
-> command (always finite, within limits) -> publish (Zenoh, non-blocking) -> record
(CSV, non-blocking) -> watchdog -> keep rate.

SIGTERM/SIGINT end the loop at the next cycle: the motor is commanded off, the log
flushed, the link closed, and ``run`` returns 0.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import time
from collections.abc import Callable, Mapping
from typing import Any

from firmware_protocol.messages import CompanionHeartbeat, CompanionState, MotorCommand
from truckd.config.schema import to_plain
from truckd.config.truck import TruckConfig
from truckd.control.controller import Controller, ControlOutput
from truckd.control.qp import ControlModel
from truckd.control.supervisor import Decision, Mode, Supervisor, SupervisorInputs
from truckd.io.devlock import DeviceLock
from truckd.io.port import Port, companion_port
from truckd.runtime.backend import Backend, claim_backend, open_backend
from truckd.runtime.command import motor_command
from truckd.runtime.faults import RuntimeFaults, wrap_solver
from truckd.runtime.mcap_log import McapLog
from truckd.runtime.notify import Notifier
from truckd.runtime.ratekeeper import RateKeeper
from truckd.runtime.realtime import RealtimeReport, setup_realtime
from truckd.runtime.recorder import Recorder
from truckd.runtime.sensors import SensorState
from truckd.runtime.telemetry import Telemetry
from truckd.sim.firmware import encoder_ticks_per_rev

log = logging.getLogger("truckd.daemon")

MODE_CODE = {Mode.INIT: 0, Mode.ACTIVE: 1, Mode.DEGRADED: 2, Mode.SAFE_STOP: 3, Mode.FAULT: 4}
"""Numeric mode in the CSV log (the log format is all numbers)."""

LOG_COLUMNS = (
    "t", "u", "v", "i", "vbat", "x",  # contract columns (always finite)
    "gap_m", "v_lead_m_s", "gap_ref", "u_ff", "u_fw", "solve_us", "mode", "enable",
    "lead_valid", "range_raw", "seq", "lateness_us", "compute_us",
)  # fmt: skip
"""Recorded columns: the contract's first (CONTRACTS.md section 3), then extras; the
gap and lead speed are extras because they are NaN while no lead is tracked."""


def _j(x: float) -> float | None:
    """JSON-safe number (None for NaN/inf)."""
    return x if math.isfinite(x) else None


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
    ) -> None:
        self.cfg = cfg
        self.rt = cfg.runtime
        self.control_cfg = cfg.control
        self.backend_name = backend or self.rt.backend
        self.duration = duration
        self.clock = clock
        self.ticks_per_rev = encoder_ticks_per_rev(
            cfg.plant.encoder_ticks_per_rev, cfg.link.encoder_ticks_per_rev
        )
        self.model = model if model is not None else ControlModel(cfg.vehicle)
        self.controller = Controller(self.model, self.control_cfg, self.ticks_per_rev)
        self.faults = RuntimeFaults()
        if self.rt.fault_injection:
            self.controller.mpc.solve = wrap_solver(  # type: ignore[method-assign]
                self.controller.mpc.solve, self.faults
            )
        self.supervisor = Supervisor(self.rt.supervisor, self.control_cfg.on_lead_lost)
        self.rk = RateKeeper(self.control_cfg.rate_hz, clock=clock)
        self.notifier = Notifier(env)
        self.sensors = SensorState(tick_len=self.controller.estimator.tick_len)
        self.u_max = self.controller.u_max
        self.period = 1.0 / self.control_cfg.rate_hz
        self.ramp_step = self.rt.stop_ramp_v_per_s * self.period
        self.claim: DeviceLock | None = None
        self.backend: Backend | None = None
        self.port: Port | None = None
        self.telemetry: Telemetry | None = None
        self.recorder: Recorder | None = None
        self.mcap: McapLog | None = None  # MCAP beside the CSV (recorder.mcap)
        self.realtime = RealtimeReport()
        self.stop_requested = False
        self.t0 = 0.0
        self.seq = 0
        self.u = 0.0
        self.enable = False
        self.decision = Decision(Mode.INIT, ())
        self.out: ControlOutput | None = None
        self.controller_errors = 0
        self.ready_sent = False
        self._last_watchdog = -math.inf
        self._next_health = 0.0
        self._states_sent = 0
        self._rate_mark = (0.0, 0)
        self._transitions: list[dict[str, object]] = []
        self._ages: dict[str, float] = {}

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
            self.telemetry.start()
            if self.rt.fault_injection:
                self.telemetry.subscribe("inject", self.faults.apply)
        if self.rt.recorder.enabled:
            self.mcap = McapLog.for_recorder(self.cfg.vehicle_id, self.rt.recorder)
            self.recorder = Recorder(self.rt.recorder, LOG_COLUMNS, sidecar=self.mcap)
            self.recorder.start()
            log.info("recording to %s", self.recorder.path)
        self.backend = open_backend(
            self.backend_name, self.cfg, self.control_cfg, self.ticks_per_rev, self.clock,
            lock=self.claim,
        )  # fmt: skip
        self.port = companion_port(self.backend.link, self.clock, self.cfg.link.timeout_periods)
        log.info(
            "truckd %s: backend %s, %.0f Hz", self.cfg.vehicle_id, self.backend_name,
            self.control_cfg.rate_hz,
        )  # fmt: skip

    def request_stop(self, signum: int = 0, _frame: object = None) -> None:
        """Signal handler: finish the current cycle, then shut down."""
        self.stop_requested = True

    def shutdown(self) -> None:
        """Motor off, notify, flush the log, close telemetry and the link.

        Motor-off goes out only on a link this daemon opened (``port`` is set only then,
        under the device lock): a daemon that failed to start sends nothing."""
        self.notifier.stopping("stopping: motor off")
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
        if self.recorder is not None and self.port is None:
            self.recorder.discard()  # did not start: no empty log left behind
        elif self.recorder is not None:
            self.recorder.stop()
            log.info("log flushed: %d rows in %s", self.recorder.rows, self.recorder.path)
        if self.telemetry is not None:
            self.publish_health(self.clock() - self.t0)
            self.telemetry.close()
        if self.backend is not None:
            self.backend.close()
        if self.claim is not None:
            self.claim.release()
        self.notifier.close()
        s = self.rk.stats()
        log.info(
            "stopped after %d cycles: misses %d, lateness p99 %.0f us, compute p99 %.0f us",
            s.cycles, s.misses, s.lateness_us_p99, s.compute_us_p99,
        )  # fmt: skip

    def run(self) -> int:
        """Start, loop until SIGTERM/SIGINT or the duration, shut down; exit code 0."""
        old = {s: signal.signal(s, self.request_stop) for s in (signal.SIGTERM, signal.SIGINT)}
        try:
            self.start()
            self.realtime = setup_realtime(self.rt.realtime, self.rt.rt_priority)
            self.loop()
        finally:
            self.shutdown()
            for s, h in old.items():
                signal.signal(s, h)
        return 0

    def loop(self) -> None:
        """Cycles until stopped."""
        self.rk.start()
        self.t0 = self.rk.cycle_start
        while not self.stop_requested:
            if self.duration is not None and self.clock() - self.t0 >= self.duration:
                break
            self.rk.begin_cycle()
            self.cycle()
            if self.faults.overrun_s > 0:
                time.sleep(self.faults.overrun_s)
            self.rk.keep_time()

    # -- one cycle -----------------------------------------------------------------
    def cycle(self) -> None:
        """read -> estimate/control -> supervise -> command -> publish -> record."""
        assert self.port is not None and self.backend is not None
        now = self.clock()
        t = now - self.t0
        try:
            received = self.port.poll()
        except Exception as exc:  # a link bug must not stop the loop: treat as silence
            log.warning("link read failed: %s", exc)
            received = []
        self.sensors.update(now, received)
        out = self.control(t)
        dec = self.supervise(now, t, out)
        u_ctrl = out.u if out is not None else None
        self.u, self.enable = motor_command(dec.mode, u_ctrl, self.u, self.ramp_step, self.u_max)
        self.controller.u_prev = self.u  # the controller's rate limit starts from what we sent
        self.send_command(dec.mode)
        self.backend.tick(self.period)
        self.publish(t, out)
        self.record(t, out)
        self.feed_watchdog(now)
        self.seq += 1

    def control(self, t: float) -> ControlOutput | None:
        s = self.sensors
        try:
            self.out = self.controller.step(t, s.encoders, s.ranges)
        except Exception as exc:  # counted as a solver failure by the supervisor
            self.controller_errors += 1
            if self.controller_errors <= 3:
                log.exception("controller failed: %s", exc)
            self.out = None
        return self.out

    def supervise(self, now: float, t: float, out: ControlOutput | None) -> Decision:
        s = self.sensors
        ages = self._ages = s.ages(now)
        reason = out.fallback_reason if out is not None else "exception"
        solver_ok = out is not None and not (reason or "").startswith("solver_")
        est = out.estimate if out is not None else None
        dec = self.supervisor.update(
            SupervisorInputs(
                t=t,
                link_up=self.backend.link.connected if self.backend else False,
                link_age=ages["link"],
                encoder_age=ages["encoder"],
                range_age=ages["range"],
                range_value=s.range_raw,
                range_fault=s.range_fault,
                speed=est.v if est is not None and est.speed_valid else 0.0,
                lead_valid=est.lead_valid if est is not None else False,
                solver_ok=solver_ok,
                loop_missed=self.rk.last_missed,
            )
        )
        self.decision = dec
        if dec.transition is not None:
            tr = dec.transition
            log.warning(
                "mode %s -> %s at t=%.3f s (%s)", tr.old.value, tr.new.value, t,
                ", ".join(tr.causes) or "all clear",
            )  # fmt: skip
            self._transitions = [*self._transitions[-9:], tr.as_dict()]
            if not self.ready_sent and tr.old == Mode.INIT:
                self.notifier.ready("link and sensors up")
                self.ready_sent = True
            self.notifier.status(f"{tr.new.value}: {', '.join(tr.causes) or 'ok'}")
            self._next_health = 0.0  # publish health now
        return dec

    def send_command(self, mode: Mode) -> None:
        assert self.port is not None
        try:
            self.port.send(MotorCommand(self.u, self.enable))
            if self.seq % 10 == 0:  # 100 ms heartbeat at 100 Hz
                self.port.send(CompanionHeartbeat(CompanionState[mode.value], 0))
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
    def publish(self, t: float, out: ControlOutput | None) -> None:
        tel, mc = self.telemetry, self.mcap
        to_tel = tel is not None and self.seq % self.rt.telemetry.state_every == 0
        if to_tel or (mc is not None and mc.wants_state(self.seq)):
            est = out.estimate if out is not None else None
            nan = math.nan
            msg: dict[str, Any] = {
                "seq": self.seq,
                "t": t,
                "mode": self.decision.mode.value,
                "v": _j(est.v if est is not None else nan),
                "gap": _j(est.gap if est is not None else nan),
                "gap_ref": _j(out.gap_ref if out is not None else nan),
                "v_lead": _j(est.v_lead if est is not None else nan),
                "u": self.u,
                "u_ff": _j(out.u_ff if out is not None else nan),
                "solve_us": _j(out.solve_time_s * 1e6 if out is not None else nan),
                "enable": self.enable,
                "ctrl": out.mode if out is not None else None,
                "fallback": out.fallback_reason if out is not None else "exception",
                "lead_valid": bool(est.lead_valid) if est is not None else False,
                "lateness_us": self.rk.last_lateness * 1e6,
                "faults": list(self.decision.causes),
                "ages_ms": {k: _j(a * 1e3) for k, a in self._ages.items()},
            }
            if mc is not None and mc.wants_state(self.seq):
                mc.record_state(t, msg)
            if tel is not None and to_tel:
                tel.publish_state(msg)
                self._states_sent += 1
        if (tel is not None or mc is not None) and t >= self._next_health:
            self.publish_health(t)
            self._next_health = t + self.rt.telemetry.health_period_s

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
            "ages_s": {k: _j(v) for k, v in ages.items()},
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
            },
            "telemetry": {"dropped": tel.dropped, "sent": tel.sent, "errors": tel.errors}
            if tel is not None
            else None,
            "recorder": self._recorder_health(),
            "realtime": self.realtime.as_dict(),
            "state_rate_hz": rate,
            "injected": {"solver": self.faults.solver_fail, "overrun_s": self.faults.overrun_s},
            "pid": os.getpid(),
        }
        extra = lambda: {"loop": rk.stats().as_dict()}  # noqa: E731
        if self.mcap is not None:
            self.mcap.record_health(t, dict(msg), extra)  # a copy: telemetry updates msg
        if tel is not None:
            tel.publish_health(msg, extra)

    def _recorder_health(self) -> dict[str, Any] | None:
        r = self.recorder
        if r is None:
            return None
        d = {"rows": r.rows, "dropped": r.dropped, "errors": r.errors, "file": str(r.path)}
        return d if self.mcap is None else {**d, "mcap": self.mcap.health()}

    def record(self, t: float, out: ControlOutput | None) -> None:
        rec = self.recorder
        if rec is None:
            return
        s = self.sensors
        nan = math.nan
        est = out.estimate if out is not None else None
        v = est.v if est is not None and math.isfinite(est.v) else 0.0
        rec.record(
            (
                t, self.u, v, s.current, s.vbat, s.x,
                est.gap if est is not None else nan,
                est.v_lead if est is not None else nan,
                out.gap_ref if out is not None else nan,
                out.u_ff if out is not None else nan,
                s.u_fw,
                out.solve_time_s * 1e6 if out is not None else nan,
                float(MODE_CODE[self.decision.mode]),
                float(self.enable),
                float(est.lead_valid) if est is not None else 0.0,
                s.range_raw if s.range_raw is not None else nan,
                float(self.seq),
                self.rk.last_lateness * 1e6,
                self.rk.last_compute * 1e6,
            )
        )  # fmt: skip
