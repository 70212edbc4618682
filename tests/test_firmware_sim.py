"""The simulated firmware in simulated time: periods, commands, the 100 ms command
timeout, range readings, encoder wrap, and every fault seen by the companion's checks."""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Callable

import pytest

from firmware_protocol.codec import Frame, encode
from firmware_protocol.messages import (
    CompanionHeartbeat,
    CompanionState,
    FirmwareFault,
    FirmwareHeartbeat,
    FirmwareState,
    MotorCommand,
    MotorFeedback,
    RangeReading,
    RangeStatus,
    WheelEncoders,
    ticks_delta,
)
from truckd.io.port import Port, Received, companion_port
from truckd.model.params import VehicleParams
from truckd.sim.firmware import (
    FirmwareSimConfig,
    RangeFn,
    SimulatedFirmware,
    constant_speed_lead,
    encoder_ticks_per_rev,
    simulated_truck,
)
from truckd.sim.plant import Plant

DT = 0.01


class Rig:
    """Plant + simulated firmware + the companion's port, in simulated time."""

    def __init__(
        self,
        params: VehicleParams,
        range_fn: RangeFn | None = None,
        mode: str = "frames",
        cfg: FirmwareSimConfig | None = None,
    ) -> None:
        self.plant = Plant(params)
        self.link, self.fw, self.wire = simulated_truck(
            self.plant,
            range_fn or constant_speed_lead(2.0, 1.0),
            mode,
            cfg,  # type: ignore[arg-type]
        )
        self.port: Port = companion_port(self.link, clock=lambda: self.fw.t)
        self.log: list[Received] = []

    def run(self, seconds: float, command: Callable[[float], MotorCommand | None]) -> None:
        for _ in range(round(seconds / DT)):
            c = command(self.fw.t)
            if c is not None:
                self.port.send(c)
            self.fw.step(DT)
            self.log += self.port.poll()

    def of(self, name: str) -> list[Received]:
        return [r for r in self.log if r.name == name]


def drive(v: float) -> Callable[[float], MotorCommand]:
    return lambda t: MotorCommand(v, True)


def test_periods_counters_and_sample_times(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(1.0, drive(3.0))
    n = Counter(r.name for r in rig.log)
    # due at t = 0, P, 2P, ... up to and including t = 1.0
    assert n == {
        "WHEEL_ENCODERS": 101,
        "MOTOR_FEEDBACK": 101,
        "RANGE": 51,
        "FIRMWARE_HEARTBEAT": 11,
    }
    st = rig.port.stats()
    assert st["rx_counter_gaps"] == 0 and st["rx_counter_errors"] == 0
    times = [r.msg.sample_time for r in rig.of("WHEEL_ENCODERS")]  # type: ignore[union-attr]
    assert all(abs(b - a - 0.01) < 1.5e-4 for a, b in itertools.pairwise(times))
    assert all(rig.port.freshness().values())


def test_command_applied_and_enable(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(1.0, drive(3.0))
    fb = rig.of("MOTOR_FEEDBACK")[-1].msg
    assert isinstance(fb, MotorFeedback)
    assert fb.u_applied == pytest.approx(3.0, abs=1e-3) and fb.status & 1
    assert rig.plant.v > 0.5
    assert rig.fw.state == FirmwareState.ACTIVE
    rig.run(0.1, lambda t: MotorCommand(3.0, False))
    fb = rig.of("MOTOR_FEEDBACK")[-1].msg
    assert isinstance(fb, MotorFeedback)
    assert fb.u_applied == 0.0 and not fb.status & 1
    assert rig.fw.state == FirmwareState.IDLE


def test_speed_from_encoders_matches_plant(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.plant.x = 65530 / rig.fw._ticks_per_m  # start just below the 16-bit wrap
    rig.run(2.0, drive(5.0))
    enc = [r.msg for r in rig.of("WHEEL_ENCODERS")]
    assert all(isinstance(e, WheelEncoders) for e in enc)
    assert enc[0].ticks_left > 65000 and enc[-1].ticks_left < 10000  # type: ignore[union-attr]
    ticks = sum(
        ticks_delta(b.ticks_left, a.ticks_left)  # type: ignore[union-attr]
        for a, b in itertools.pairwise(enc)
    )
    tick_len = 2 * math.pi * params.r_w / 512
    assert ticks * tick_len == pytest.approx(rig.plant.x - 65530 * tick_len, abs=2 * tick_len)


def test_command_timeout_motor_off_and_fault_bit(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.5, drive(3.0))  # last command received at t = 0.49
    rig.run(0.3, lambda t: None)
    fb = {round(r.t, 3): r.msg for r in rig.of("MOTOR_FEEDBACK")}
    assert fb[0.58].u_applied == pytest.approx(3.0, abs=1e-3)  # type: ignore[union-attr]
    assert fb[0.59].u_applied == 0.0  # type: ignore[union-attr]
    assert rig.fw.stats.cmd_timeouts == 1
    hb = [r.msg for r in rig.of("FIRMWARE_HEARTBEAT") if r.t > 0.6]
    assert hb and all(
        isinstance(h, FirmwareHeartbeat)
        and h.state == FirmwareState.FAILSAFE
        and h.faults & FirmwareFault.CMD_TIMEOUT
        for h in hb
    )
    # valid commands again: drives, and the bit clears after one heartbeat reported it
    rig.run(0.5, drive(2.0))
    last = rig.of("FIRMWARE_HEARTBEAT")[-1].msg
    assert isinstance(last, FirmwareHeartbeat)
    assert last.state == FirmwareState.ACTIVE and not last.faults & FirmwareFault.CMD_TIMEOUT


def test_no_command_ever_motor_stays_off(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.5, lambda t: None)
    assert rig.plant.v == 0.0
    hb = rig.of("FIRMWARE_HEARTBEAT")[-1].msg
    assert isinstance(hb, FirmwareHeartbeat)
    assert hb.state == FirmwareState.IDLE and hb.faults & FirmwareFault.CMD_TIMEOUT


def test_voltage_clamped_to_battery(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.2, drive(30.0))
    fb = rig.of("MOTOR_FEEDBACK")[-1].msg
    assert isinstance(fb, MotorFeedback)
    assert fb.u_applied == pytest.approx(params.V_batt, abs=1e-3)
    assert any(
        r.msg.faults & FirmwareFault.CMD_INVALID  # type: ignore[union-attr]
        for r in rig.of("FIRMWARE_HEARTBEAT")
    )


def test_corrupt_commands_rejected_and_do_not_feed_the_timeout(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.2, drive(3.0))
    good = encode(MotorCommand(3.0, True), 5)
    bad = Frame(good.can_id, good.data[:-1] + bytes((good.data[-1] ^ 0x10,)))

    def corrupt(t: float) -> None:
        rig.link.send(bad)

    rig.run(0.3, corrupt)  # type: ignore[arg-type]
    assert rig.fw.voltage == 0.0 and rig.fw.state == FirmwareState.FAILSAFE
    hb = rig.of("FIRMWARE_HEARTBEAT")[-1].msg
    assert isinstance(hb, FirmwareHeartbeat)
    assert hb.faults & FirmwareFault.CMD_CHECKSUM and hb.cmd_errors == 30


def test_range_readings(params: VehicleParams) -> None:
    def lead(t: float, x: float) -> float | None:
        return None if t > 0.5 else (9.0 if t > 0.3 else 2.0 + t - x)

    rig = Rig(params, lead, cfg=FirmwareSimConfig(range_max=4.0, range_noise=0.0))
    rig.run(0.8, drive(3.0))
    for r in rig.of("RANGE"):
        m = r.msg
        assert isinstance(m, RangeReading)
        if r.t <= 0.3 + 1e-9:
            assert m.status == RangeStatus.VALID and m.gap is not None
        else:
            assert m.status == RangeStatus.NO_TARGET and m.gap is None
    # the reading at t = 0.2 is the true gap (x from the plant at that instant)
    first = rig.of("RANGE")[0].msg
    assert isinstance(first, RangeReading) and first.distance == pytest.approx(2.0, abs=1e-3)


def test_companion_heartbeat_timeout_bit(params: VehicleParams) -> None:
    rig = Rig(params)

    def with_hb(t: float) -> MotorCommand:
        if round(t / DT) % 10 == 0:
            rig.port.send(CompanionHeartbeat(CompanionState.ACTIVE))
        return MotorCommand(1.0, True)

    rig.run(1.0, with_hb)
    hb = rig.of("FIRMWARE_HEARTBEAT")[-1].msg
    assert isinstance(hb, FirmwareHeartbeat) and not hb.faults & FirmwareFault.COMPANION_TIMEOUT
    rig.run(1.0, drive(1.0))
    hb = rig.of("FIRMWARE_HEARTBEAT")[-1].msg
    assert isinstance(hb, FirmwareHeartbeat) and hb.faults & FirmwareFault.COMPANION_TIMEOUT


# -- fault injection, each seen by the companion's receive checks ------------------------


def test_fault_drop(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.2, drive(2.0))
    rig.fw.apply_fault({"fault": "drop", "message": "RANGE", "count": 3})
    rig.run(0.5, drive(2.0))
    assert rig.port.stats()["rx_counter_gaps"] == 3
    assert rig.fw.stats.frames_dropped == 3


def test_fault_drop_until_cleared_goes_stale(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.2, drive(2.0))
    rig.fw.apply_fault({"fault": "drop", "message": "WHEEL_ENCODERS"})
    rig.run(0.2, drive(2.0))
    assert not rig.port.fresh("WHEEL_ENCODERS") and rig.port.fresh("RANGE")
    assert rig.port.stats()["rx_timeouts"] == 1
    rig.fw.apply_fault({"fault": "drop", "message": "WHEEL_ENCODERS", "count": 0})
    rig.run(0.05, drive(2.0))
    assert rig.port.fresh("WHEEL_ENCODERS")


def test_fault_freeze(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.3, drive(4.0))
    rig.fw.apply_fault({"fault": "freeze", "message": "RANGE", "on": True})
    n0 = len(rig.of("RANGE"))
    rig.run(0.5, drive(4.0))
    frozen = [r.msg for r in rig.of("RANGE")[n0:]]
    assert len(frozen) == 25 and len(set(frozen)) == 1  # same values, fresh counters
    assert rig.port.stats()["rx_counter_errors"] == 0
    rig.fw.apply_fault({"fault": "freeze", "message": "RANGE", "on": False})
    rig.run(0.1, drive(4.0))
    assert rig.of("RANGE")[-1].msg != frozen[0]


def test_fault_checksum(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.1, drive(2.0))
    rig.fw.apply_fault({"fault": "checksum", "message": "WHEEL_ENCODERS"})
    n0 = len(rig.of("WHEEL_ENCODERS"))
    rig.run(0.2, drive(2.0))
    assert len(rig.of("WHEEL_ENCODERS")) == n0
    assert rig.port.stats()["rx_checksum_errors"] == 20
    assert not rig.port.fresh("WHEEL_ENCODERS")


def test_fault_counter(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.1, drive(2.0))
    rig.fw.apply_fault({"fault": "counter", "message": "MOTOR_FEEDBACK"})
    n0 = len(rig.of("MOTOR_FEEDBACK"))
    rig.run(0.2, drive(2.0))
    # the first frame with the stuck value passes, then none (not even after the
    # freshness timeout: a repeated counter is never accepted)
    assert len(rig.of("MOTOR_FEEDBACK")) == n0 + 1
    assert rig.port.stats()["rx_counter_errors"] == 19
    assert not rig.port.fresh("MOTOR_FEEDBACK")


@pytest.mark.parametrize("mode", ["bytes", "frames"])
def test_fault_garbage(params: VehicleParams, mode: str) -> None:
    rig = Rig(params, mode=mode)
    rig.run(0.1, drive(2.0))
    for _ in range(10):
        rig.fw.apply_fault({"fault": "garbage", "bytes": 50})
        rig.run(0.05, drive(2.0))
    st = rig.port.stats()
    assert st["rx_counter_gaps"] == 0  # no intact frame lost
    assert rig.fw.stats.garbage_sent == 500
    if mode == "bytes":
        assert st["framing_resyncs"] >= 10 and st["framing_bytes_discarded"] >= 400
    else:
        errors = st["rx_unknown_ids"] + st["rx_length_errors"] + st["rx_checksum_errors"]
        assert errors == 500


def test_fault_silent(params: VehicleParams) -> None:
    rig = Rig(params)
    rig.run(0.2, drive(2.0))
    rig.fw.apply_fault({"fault": "silent", "on": True})
    n0 = len(rig.log)
    rig.run(0.6, drive(2.0))  # > 5 heartbeat periods
    assert len(rig.log) == n0
    assert not any(rig.port.freshness().values())
    assert rig.port.stats()["rx_timeouts"] == 4
    assert rig.fw.state == FirmwareState.ACTIVE  # still listening and driving
    rig.fw.apply_fault({"fault": "clear"})
    rig.run(0.2, drive(2.0))
    assert all(rig.port.freshness().values())


@pytest.mark.parametrize("mode", ["bytes", "frames"])
def test_fault_disconnect_and_come_back(params: VehicleParams, mode: str) -> None:
    rig = Rig(params, mode=mode)
    rig.run(0.2, drive(2.0))
    rig.fw.apply_fault({"fault": "disconnect", "duration": 0.3})
    rig.run(0.2, drive(2.0))
    assert not rig.link.connected
    assert rig.fw.state == FirmwareState.FAILSAFE  # no commands got through
    rig.run(0.3, drive(2.0))
    assert rig.link.connected and rig.fw.state == FirmwareState.ACTIVE
    st = rig.port.stats()
    assert st["disconnects"] == 1 and st["reconnects"] == 1
    assert all(rig.port.freshness().values())


@pytest.mark.parametrize(
    "cmd",
    [
        {"fault": "bogus", "message": "RANGE"},
        {"fault": "drop", "message": "MOTOR_CMD"},
        {"fault": "drop", "message": "RANGE", "count": -2},
        {"fault": "garbage", "bytes": "many"},
        {"fault": "disconnect", "duration": -1},
        {},
    ],
)
def test_bad_fault_commands(params: VehicleParams, cmd: dict[str, object]) -> None:
    rig = Rig(params)
    with pytest.raises(ValueError):
        rig.fw.apply_fault(cmd)


def test_step_rejects_bad_dt(params: VehicleParams) -> None:
    rig = Rig(params)
    for dt in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError):
            rig.fw.step(dt)


def test_disconnect_needs_a_hook(params: VehicleParams) -> None:
    from truckd.io.inproc import inproc_pair

    _, mcu, _ = inproc_pair()
    fw = SimulatedFirmware(Plant(params), constant_speed_lead(1.0, 0.0), mcu)
    with pytest.raises(ValueError, match="unplug"):
        fw.apply_fault({"fault": "disconnect", "duration": 0.1})


def test_encoder_resolution_choice() -> None:
    assert encoder_ticks_per_rev(0, 512) == 512
    assert encoder_ticks_per_rev(100, 512) == 100
