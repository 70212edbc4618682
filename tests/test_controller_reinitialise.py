"""After a loop stall the controller forgets everything it learned from past cycles: a
re-initialised controller drives exactly as a new one does on the same inputs."""

from __future__ import annotations

import gc
import math

from truckd.config.truck import load_config
from truckd.control.controller import Controller
from truckd.control.estimator import EncoderSample, RangeSample
from truckd.control.mpc import MpcSolver
from truckd.control.qp import ControlModel
from truckd.model.effects import Effects

TICKS = 512


def drive(ctrl: Controller, t0: float, cycles: int, v: float, gap0: float) -> list[float]:
    """Feed a truck at speed v (m/s) behind a lead braking at 0.8 m/s^2; the commands."""
    p = ctrl.model.params
    dt = ctrl.cfg.period
    per_tick = 2.0 * math.pi * p.r_w / TICKS
    out = []
    for k in range(cycles):
        t = t0 + k * dt
        x = v * t
        ticks = round(x / per_tick)
        v_lead = max(v - 0.8 * k * dt, 0.0)
        gap = gap0 + (v_lead - v) * k * dt
        enc = [EncoderSample(ticks, ticks, t)]
        rng = [RangeSample(gap, t)]
        out.append(ctrl.step(t, enc, rng, current=1.0, vbat=7.0).u)
    return out


def test_a_reinitialised_controller_drives_as_a_new_one() -> None:
    tc = load_config()
    eff = Effects(dead_zone=0.8, input_delay=0.05, battery_sag=0.1)
    model = ControlModel(tc.vehicle, eff)
    cfg = tc.control.in_simulated_time()  # judged by what the solver did, not its time
    # Solvers of earlier tests in this process may hold the compiled instances: then one of
    # the two controllers would run the Python path, which agrees to 1e-9 V, not to the
    # bit.  Both on the same path: compiled when two instances are free, else Python.
    gc.collect()
    used, fresh = Controller(model, cfg, TICKS), Controller(model, cfg, TICKS)
    if used.mpc.backend != fresh.mpc.backend:
        for c in (used, fresh):
            c.mpc = MpcSolver(model, cfg, compiled=False)
    drive(used, 0.0, 150, 0.6, 0.9)  # learns: plan, pipeline, dead-zone state, lead accel
    used.reinitialise()
    assert drive(used, 5.0, 60, 0.3, 1.2) == drive(fresh, 5.0, 60, 0.3, 1.2)
