"""Closed-loop runner: the daemon's own companion cycle drives the simulated truck
through the simulated firmware and the real protocol on an in-process link.

Each cycle (period ``1 / control.rate_hz``): poll the checked messages, run
:class:`~truckd.runtime.cycle.CompanionCycle` (sensors -> controller -> supervisor ->
motor command, exactly as ``truckd run`` on the car), send ``MOTOR_CMD`` (with its
``enable``) and the heartbeat the cycle asks for, then let the simulated firmware advance
the plant by one period.

In simulated time (the default, as fast as the machine goes) the run is deterministic:
the solver is judged by what it did (status, iterations), not against the wall clock, and
the loop never misses a deadline; so the same command gives the same result on an idle and
on a loaded machine.  The wall time is still measured and reported (``solve_us_*``:
OSQP's own time; ``step_us_p99``: poll + step + send, ``time.perf_counter``;
``deadline_misses``: steps slower than the period).  ``realtime=True`` paces each cycle
on absolute wall-clock deadlines (the results then still do not depend on the load).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from truckd.config.runtime import RuntimeConfig
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.platoon import Plan
from truckd.control.qp import ControlModel
from truckd.control.supervisor import SupervisorConfig, time_in_modes
from truckd.io.config import ENCODER_TICKS_PER_REV
from truckd.io.port import companion_port
from truckd.model.params import VehicleParams
from truckd.runtime.cycle import CompanionCycle, CycleInputs
from truckd.runtime.platoon_link import cycle_plan
from truckd.sim.firmware import FirmwareSimConfig
from truckd.sim.plant import PlantConfig
from truckd.sim.scenarios import Scenario, World
from truckd.sim.truck import TruckSpec, build_truck

if TYPE_CHECKING:
    from truckd.config.truck import TruckConfig

STEADY_AFTER_S = 5.0
"""``gap_error_rms_m`` is taken after this time (reference section 1)."""

TRUTH_COLUMNS = ("v_true", "gap_true", "v_lead_true", "x_true", "i_true")
"""The plant's truth, appended to each log row of a trace (m/s, m, m/s, m, A)."""


@dataclass
class Trace:
    """Time series of a run (SI): true gap and speeds, reference gap, command, mode."""

    t: list[float] = field(default_factory=list)
    gap: list[float] = field(default_factory=list)
    gap_ref: list[float] = field(default_factory=list)
    v: list[float] = field(default_factory=list)
    v_lead: list[float] = field(default_factory=list)
    u: list[float] = field(default_factory=list)
    u_ff: list[float] = field(default_factory=list)
    mode: list[str] = field(default_factory=list)
    gap_est: list[float] = field(default_factory=list)
    supervisor: list[str] = field(default_factory=list)
    """The supervisor's mode each cycle (``mode`` is the controller's)."""
    rows: list[tuple[float, ...]] = field(default_factory=list)
    """The daemon's log row each cycle (:data:`~truckd.runtime.cycle.LOG_COLUMNS`) with
    the truth appended (:data:`TRUTH_COLUMNS`)."""
    plans: list[Plan | None] = field(default_factory=list)
    """The plan the daemon would publish after each cycle (the MPC's predicted speeds,
    standstill while holding, None on a fallback), stamped with the simulated time and
    without a vehicle id (:func:`truckd.runtime.platoon_link.cycle_plan`)."""


@dataclass(frozen=True)
class SimSetup:
    """Everything a run needs: the plant's truth and the controller's belief."""

    plant_params: VehicleParams
    plant_config: PlantConfig
    control: ControlConfig
    model: ControlModel
    ticks_per_rev: int = ENCODER_TICKS_PER_REV
    """``link.encoder_ticks_per_rev`` (the plant's own encoder, when it models one, wins)."""
    firmware: FirmwareSimConfig | None = None
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    stop_ramp_v_per_s: float = field(default_factory=lambda: RuntimeConfig().stop_ramp_v_per_s)
    """The SAFE_STOP ramp (V/s, ``runtime.stop_ramp_v_per_s``; its default there)."""

    @classmethod
    def from_config(cls, cfg: TruckConfig, model: ControlModel | None = None) -> SimSetup:
        """The simulated truck of a configuration (:func:`truckd.sim.truck.truck_spec`)
        driven by ``model`` (default: the configured vehicle, no effects)."""
        return cls(
            cfg.plant_vehicle,
            cfg.plant,
            cfg.control,
            model if model is not None else ControlModel(cfg.vehicle),
            ticks_per_rev=cfg.link.encoder_ticks_per_rev,
            supervisor=cfg.runtime.supervisor,
            stop_ramp_v_per_s=cfg.runtime.stop_ramp_v_per_s,
        )

    @property
    def truck(self) -> TruckSpec:
        """The simulated truck (plant, firmware, sensor limits) this setup drives."""
        return TruckSpec.of(
            self.plant_params, self.plant_config, self.control, self.ticks_per_rev, self.firmware
        )


def _percentile(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else math.nan


def run_scenario(
    sc: Scenario, setup: SimSetup, duration: float | None = None, realtime: bool = False
) -> tuple[dict[str, Any], Trace]:
    """Run one scenario; returns the contract metrics (reference section 1) and a trace."""
    cfg = setup.control
    dt = cfg.period
    dur = sc.duration if duration is None else duration
    world = World(sc)
    spec = setup.truck
    truck = build_truck(spec, world.range_fn, v0=sc.v0)
    plant, fw, link = truck.plant, truck.firmware, truck.link
    assert link is not None
    port = companion_port(link, clock=lambda: plant.t)
    cyc = CompanionCycle(
        setup.model,
        cfg,
        setup.supervisor,
        spec.firmware.ticks_per_rev,
        setup.stop_ramp_v_per_s,
        time_budget=False,  # simulated time: judged by what the solver did
    )
    tr = Trace()
    solve_us: list[float] = []
    step_us: list[float] = []
    deadline_misses = 0
    n_cycles = max(1, round(dur / dt))
    wall0 = time.monotonic()
    for k in range(n_cycles):
        t = plant.t
        t0 = time.perf_counter()
        out = cyc.step(CycleInputs(t, port.poll(), link.connected))
        port.send(out.command)
        if out.heartbeat is not None:
            port.send(out.heartbeat)
        elapsed = time.perf_counter() - t0
        step_us.append(elapsed * 1e6)
        c = out.control
        if c is not None and c.solve_iterations > 0:
            solve_us.append(c.solve_time_s * 1e6)
        deadline_misses += elapsed > dt
        gap = world.gap(t, plant.x)
        vl = world.v_lead(t)
        tr.t.append(t)
        tr.gap.append(math.nan if gap is None else gap)
        tr.gap_ref.append(cfg.d_0 + cfg.time_headway * plant.v)
        tr.v.append(plant.v)
        tr.v_lead.append(math.nan if vl is None else vl)
        tr.u.append(out.command.voltage)
        tr.u_ff.append(c.u_ff if c is not None else math.nan)
        tr.mode.append(c.mode if c is not None else "exception")
        tr.gap_est.append(c.estimate.gap if c is not None else math.nan)
        tr.supervisor.append(out.mode.value)
        tr.rows.append(
            (*cyc.log_row(out), plant.v, tr.gap[-1], tr.v_lead[-1], plant.x, plant.motor.i)
        )
        tr.plans.append(cycle_plan(cyc, out, t))
        fw.step(dt)
        if realtime:
            delay = wall0 + (k + 1) * dt - time.monotonic()
            if delay > 0.0:
                time.sleep(delay)
    metrics = _metrics(sc, cfg, tr, solve_us, step_us, deadline_misses, cyc.controller)
    modes = tr.supervisor
    return {
        **metrics,
        # s in each supervisor mode (every mode named) and the count of mode changes
        "mode_time_s": time_in_modes(modes, dt),
        "transitions": len(cyc.supervisor.transitions),
    }, tr


def _metrics(
    sc: Scenario,
    cfg: ControlConfig,
    tr: Trace,
    solve_us: list[float],
    step_us: list[float],
    deadline_misses: int,
    ctrl: Controller,
) -> dict[str, Any]:
    gaps = np.array(tr.gap)
    has_gap = np.isfinite(gaps)
    t = np.array(tr.t)
    err = gaps - np.array(tr.gap_ref)
    in_range = has_gap & (gaps <= cfg.estimator.range_max) & (t >= STEADY_AFTER_S)
    last = has_gap & (t >= t[-1] - 2.0) if len(t) else has_gap
    min_gap = float(np.min(gaps[has_gap])) if has_gap.any() else None
    return {
        "scenario": sc.name,
        "duration_s": round(float(t[-1] + cfg.period) if len(t) else 0.0, 6),
        "cycles": len(tr.t),
        "collision": bool(min_gap is not None and min_gap <= 0.0),
        "min_gap_m": min_gap,
        "gap_error_rms_m": float(np.sqrt(np.mean(err[in_range] ** 2))) if in_range.any() else None,
        "max_abs_voltage_v": float(np.max(np.abs(tr.u))) if tr.u else 0.0,
        "solve_us_p50": _percentile(solve_us, 50),
        "solve_us_p99": _percentile(solve_us, 99),
        "step_us_p99": _percentile(step_us, 99),
        "solver_failures": ctrl.solver_failures,
        "deadline_misses": deadline_misses,
        # Extensions (not in the contract's minimum):
        "fallback_cycles": ctrl.fallback_cycles,
        "braking_cycles": ctrl.braking_cycles,
        "final_gap_error_m": float(np.mean(err[last])) if last.any() else None,
        "final_speed_m_s": float(np.mean(np.array(tr.v)[-50:])) if tr.v else 0.0,
        "all_finite": bool(np.all(np.isfinite(tr.u))),
        "feedforward": cfg.feedforward,
        # the minimum gap is a soft constraint of the MPC: how long the true gap was below it
        "time_below_d_min_s": round(float(np.sum(gaps[has_gap] < cfg.d_min)) * cfg.period, 6),
    }
