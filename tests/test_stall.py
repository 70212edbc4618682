"""A loop stall (the process stopped, the host frozen): detected at the cycle level with
an injected clock, the control state re-initialised (estimator restarted, MPC warm start
dropped), INIT with the motor off until the sensors are fresh again, then ACTIVE."""

from __future__ import annotations

from pathlib import Path

import pytest
from runtime_support import write_config

from firmware_protocol.messages import MotorFeedback, RangeReading, RangeStatus, WheelEncoders
from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.control.supervisor import Mode
from truckd.errors import InputError
from truckd.io.port import Received
from truckd.runtime.cycle import CompanionCycle, CycleInputs, CycleOutputs

PERIOD = 0.01


def messages(t: float, ticks: int, gap: float) -> list[Received]:
    return [
        Received(t, "WHEEL_ENCODERS", WheelEncoders(ticks, ticks, t)),
        Received(t, "MOTOR_FEEDBACK", MotorFeedback(1.0, 7.2, 0.0)),
        Received(t, "RANGE", RangeReading(gap, RangeStatus.VALID, t)),
    ]


class Clocked:
    """A companion cycle driven by an injected clock: a truck creeping behind a lead."""

    def __init__(self, stall_limit_s: float) -> None:
        tc = load_config()
        self.cyc = CompanionCycle(
            ControlModel(tc.vehicle), tc.control, tc.runtime.supervisor, tc.ticks_per_rev,
            tc.runtime.stop_ramp_v_per_s, time_budget=False, stall_limit_s=stall_limit_s,
        )  # fmt: skip
        self.recovery_s = tc.runtime.supervisor.recovery_s
        self.now = 0.0
        self.ticks = 0

    def step(self, dt: float = PERIOD) -> CycleOutputs:
        self.now += dt
        self.ticks += 2
        return self.cyc.step(CycleInputs(self.now, messages(self.now, self.ticks, 2.0)))


def test_a_stall_restarts_control_in_init_then_drives_again() -> None:
    c = Clocked(stall_limit_s=5 * PERIOD)
    outs = [c.step() for _ in range(100)]
    assert outs[-1].mode == Mode.ACTIVE and outs[-1].command.enable
    assert c.cyc.controller.mpc.has_warm_start
    est = c.cyc.controller.estimator
    assert all(o.stall_s == 0.0 for o in outs)
    # late cycles below the limit are no stall
    assert c.step(4 * PERIOD).stall_s == 0.0 and c.cyc.stalls == 0
    # the process was stopped for 2 s
    out = c.step(2.0)
    assert out.stall_s == pytest.approx(2.0)
    assert (c.cyc.stalls, c.cyc.last_stall_s) == (1, pytest.approx(2.0))
    assert out.mode == Mode.INIT and "loop_stall" in out.decision.causes
    assert (out.command.voltage, out.command.enable) == (0.0, False)
    assert c.cyc.controller.estimator is not est  # restarted
    assert not c.cyc.controller.mpc.has_warm_start  # the first solve after it is cold
    # INIT, motor off, for the recovery time; then ACTIVE again without another stall
    after = [c.step() for _ in range(round(c.recovery_s / PERIOD) + 20)]
    held = [o for o in after if o.t - out.t <= c.recovery_s - 1e-9]
    assert held and all(o.mode == Mode.INIT and not o.command.enable for o in held)
    assert after[-1].mode == Mode.ACTIVE and after[-1].command.enable
    assert c.cyc.stalls == 1 and all(o.stall_s == 0.0 for o in after)


def test_without_a_limit_a_stall_is_only_a_late_cycle() -> None:
    """The control experiment: the same 2 s gap with no limit drives on (ACTIVE)."""
    c = Clocked(stall_limit_s=float("inf"))
    for _ in range(100):
        c.step()
    out = c.step(2.0)
    assert out.stall_s == 0.0 and c.cyc.stalls == 0
    assert out.mode != Mode.INIT


def test_the_stall_limit_is_validated(tmp_path: Path) -> None:
    p = write_config(tmp_path / "t.yaml", {"runtime": {"stall_limit_s": 0.015}})
    with pytest.raises(InputError, match=r"runtime\.stall_limit_s.*two control periods"):
        load_config(p)
    p = write_config(tmp_path / "t.yaml", {"runtime": {"stall_limit_s": -1.0}})
    with pytest.raises(InputError, match="stall_limit_s"):
        load_config(p)
    p = write_config(tmp_path / "t.yaml", {"runtime": {"stall_limit_s": 0.02}})
    assert load_config(p).runtime.stall_limit_s == 0.02
