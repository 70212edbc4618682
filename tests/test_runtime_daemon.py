"""The daemon's pieces (sensor bookkeeping, motor command) and whole in-process and
subprocess runs on the sim backend: clean stop, recorded log, SIGTERM."""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from runtime_support import write_config

from firmware_protocol.messages import FirmwareState, RangeReading, RangeStatus, WheelEncoders
from truckd.config.truck import default_config_path, load_config
from truckd.control.supervisor import Mode
from truckd.io.port import Received
from truckd.logfile import read_log
from truckd.runtime.command import motor_command
from truckd.runtime.daemon import MODE_CODE, Daemon
from truckd.runtime.realtime import unfreeze_gc
from truckd.runtime.sensors import SensorState


def rx(t: float, msg: object) -> Received:
    return Received(t, type(msg).__name__, msg)  # type: ignore[arg-type]


def test_sensors_ignore_nan_and_repeated_samples() -> None:
    s = SensorState(tick_len=0.001)
    s.update(0.0, [rx(0.0, RangeReading(1.5, RangeStatus.VALID, 0.10))])
    assert s.t_range == 0.0 and s.range_raw == 1.5 and len(s.ranges) == 1
    s.update(0.02, [rx(0.02, RangeReading(math.nan, RangeStatus.VALID, 0.12))])
    assert s.invalid == 1 and s.t_range == 0.0 and s.ranges == []
    s.update(0.04, [rx(0.04, RangeReading(1.5, RangeStatus.VALID, 0.10))])  # frozen
    assert s.repeated == 1 and s.t_range == 0.0
    s.update(0.06, [rx(0.06, RangeReading(0.0, RangeStatus.NO_TARGET, 0.16))])
    assert s.t_range == 0.06 and s.range_raw is None and s.ranges[0].distance is None


def test_sensors_range_fault_is_not_no_target() -> None:
    s = SensorState(tick_len=0.001)
    s.update(0.0, [rx(0.0, RangeReading(1.5, RangeStatus.VALID, 0.10))])
    assert not s.range_fault
    s.update(0.02, [rx(0.02, RangeReading(0.0, RangeStatus.SENSOR_FAULT, 0.12))])
    assert s.range_fault and s.range_faults == 1
    assert s.ranges == [] and s.range_raw is None  # no sample for the estimator
    s.update(0.04, [rx(0.04, RangeReading(1.4, RangeStatus.VALID, 0.14))])
    assert not s.range_fault and s.ranges[0].distance == 1.4


def test_sensors_integrate_distance_across_wrap() -> None:
    s = SensorState(tick_len=0.002)
    s.update(0.0, [rx(0.0, WheelEncoders(65530, 65530, 0.01))])
    s.update(0.01, [rx(0.01, WheelEncoders(10, 10, 0.02))])  # +16 ticks through the wrap
    assert s.x == pytest.approx(16 * 0.002)
    s.update(0.02, [rx(0.02, WheelEncoders(20, 10, 0.03, status=2))])  # right wheel faulty
    assert s.x == pytest.approx(26 * 0.002)
    assert s.ages(0.05)["encoder"] == pytest.approx(0.03)


floats = st.floats(allow_nan=True, allow_infinity=True)


@given(st.sampled_from(list(Mode)), st.one_of(st.none(), floats), floats, floats)
def test_motor_command_always_finite_and_within_limits(
    mode: Mode, u_ctrl: float | None, u_prev: float, ramp: float
) -> None:
    u, enable = motor_command(mode, u_ctrl, u_prev, ramp, 7.2)
    assert math.isfinite(u) and abs(u) <= 7.2
    if mode in (Mode.INIT, Mode.FAULT):
        assert (u, enable) == (0.0, False)
    if mode == Mode.SAFE_STOP and math.isfinite(u_prev):
        assert abs(u) <= abs(u_prev) and u * u_prev >= 0  # towards 0, never through it


def test_safe_stop_ramps_to_zero() -> None:
    u, seq = 6.0, []
    for _ in range(20):
        u, _en = motor_command(Mode.SAFE_STOP, 5.0, u, 0.6, 7.2)
        seq.append(u)
    assert seq[:3] == pytest.approx([5.4, 4.8, 4.2])
    assert seq[-1] == 0.0


def test_in_process_run_records_a_contract_log(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger="truckd.daemon")
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), "sim", duration=2.0, env={})
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    assert d.recorder is not None and d.recorder.path is not None
    log = read_log(d.recorder.path, require=("t", "u", "v"))
    n = d.rk.cycles
    assert len(log) == n  # nothing lost: a row for every cycle run
    assert n + d.rk.skipped_periods >= 195  # every period of the 2 s run, or counted skipped
    assert np.all(np.diff(log["t"]) > 0)
    assert np.all(np.abs(log["u"]) <= d.u_max)
    assert MODE_CODE[Mode.ACTIVE] in set(log["mode"].astype(int))
    assert log["v"].max() > 0.3  # it drove
    # DEGRADED: a late solve; INIT only when the host stalled the loop (counted, and the
    # supervisor's cause), the designed reaction to a stall
    stalled = d.companion.stalls > 0 and "loop_stall" in d.decision.causes
    assert d.decision.mode in (Mode.ACTIVE, Mode.DEGRADED) or stalled, d.decision
    # the start into ACTIVE is news (INFO); a transition with a cause is a warning
    modes = [r for r in caplog.records if r.getMessage().startswith("mode ")]
    assert any("INIT -> ACTIVE" in r.getMessage() for r in modes), modes
    for r in modes:
        clear = "-> ACTIVE" in r.getMessage() and r.getMessage().endswith("(all clear)")
        assert r.levelno == (logging.INFO if clear else logging.WARNING), r.getMessage()


def test_sigterm_stops_cleanly_with_exit_0(tmp_path: Path) -> None:
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    # --duration: a daemon that never drives ends on its own and the test fails, not hangs
    proc = subprocess.Popen(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg_path),
         "--backend", "sim", "--duration", "60"],
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    try:
        head = []
        for line in proc.stderr:  # wait until it drives
            head.append(line)
            if "-> ACTIVE" in line:
                break
        else:
            pytest.fail("never ACTIVE: " + "".join(head))
        time.sleep(1.0)  # drive for a while (about 100 rows)
        t_term = time.monotonic()
        os.kill(proc.pid, signal.SIGTERM)
        rest = proc.stderr.read()
        assert proc.wait(timeout=20) == 0, rest
        assert time.monotonic() - t_term < 15.0  # stopped by the signal, not the duration
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
        proc.stderr.close()
    assert "log flushed" in rest
    files = sorted((tmp_path / "logs").glob("*.csv"))
    assert len(files) == 1
    log = read_log(files[0])
    assert len(log) >= 50
    # the last recorded command before the stop is finite and the log ends cleanly
    assert math.isfinite(log["u"][-1])


def test_sigterm_while_driving_commands_the_motor_off(tmp_path: Path) -> None:
    """The real SIGTERM handler, raised while the truck drives: the loop ends after that
    cycle, run() returns 0 and the simulated firmware received 0 V with the driver
    disabled (IDLE by command, not FAILSAFE by its 100 ms timeout)."""
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), "sim", duration=30.0, env={})
    signalled: list[tuple[float, int]] = []
    one_cycle = d.cycle

    def cycle_then_sigterm() -> None:
        one_cycle()
        assert d.backend is not None and d.backend.firmware is not None
        fw = d.backend.firmware
        if not signalled and d.decision.mode == Mode.ACTIVE and fw.enabled and fw.voltage > 0.5:
            signalled.append((fw.voltage, d.rk.cycles))
            os.kill(os.getpid(), signal.SIGTERM)

    d.cycle = cycle_then_sigterm  # type: ignore[method-assign]
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    assert signalled, "never drove"
    assert d.rk.cycles == signalled[0][1] + 1  # the signalled cycle was the last one
    assert d.backend is not None and d.backend.firmware is not None
    fw = d.backend.firmware
    assert (fw.voltage, fw.enabled, fw.state) == (0.0, False, FirmwareState.IDLE)
    assert fw.stats.cmd_timeouts == 0
    assert signal.getsignal(signal.SIGTERM) != d.request_stop  # handler restored


def test_an_exception_in_the_loop_still_commands_the_motor_off(tmp_path: Path) -> None:
    """A bug that escapes a cycle ends the daemon (exit 1 via the CLI, systemd restarts
    it), but only after the motor is commanded off."""
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), "sim", duration=30.0, env={})
    one_cycle = d.cycle

    def cycle_then_fail() -> None:
        one_cycle()
        assert d.backend is not None and d.backend.firmware is not None
        fw = d.backend.firmware
        if d.decision.mode == Mode.ACTIVE and fw.enabled and fw.voltage > 0.5:
            raise RuntimeError("injected bug")

    d.cycle = cycle_then_fail  # type: ignore[method-assign]
    try:
        with pytest.raises(RuntimeError, match="injected bug"):
            d.run()
    finally:
        unfreeze_gc()
    assert d.backend is not None and d.backend.firmware is not None
    fw = d.backend.firmware
    assert (fw.voltage, fw.enabled, fw.state) == (0.0, False, FirmwareState.IDLE)
    assert signal.getsignal(signal.SIGTERM) != d.request_stop  # handler restored


def test_bad_config_is_exit_2(tmp_path: Path) -> None:
    cfg_path = write_config(tmp_path / "truck.yaml", {"runtime": {"backend": "carrier-pigeon"}})
    r = subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(cfg_path)],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2
    assert "runtime.backend" in r.stderr and "carrier-pigeon" in r.stderr


@pytest.mark.parametrize(
    ("backend", "link"),
    [
        ("can", {"can_interface": "virtual", "can_channel": "truckd-test-nopeer"}),
        ("serial", {"serial_device": "/nonexistent/ttyACM9"}),
    ],
)
def test_without_a_microcontroller_stays_init_motor_off(
    tmp_path: Path, backend: str, link: dict[str, str]
) -> None:
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"link": link, "runtime": {"realtime": False, "telemetry": {"enabled": False},
                                   "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), backend, duration=1.0, env={})
    try:
        assert d.run() == 0
    finally:
        unfreeze_gc()
    assert d.decision.mode in (Mode.INIT, Mode.FAULT)
    assert d.supervisor.transitions == [] or all(
        tr.new in (Mode.INIT, Mode.FAULT) for tr in d.supervisor.transitions
    )
    assert d.recorder is not None and d.recorder.path is not None
    log = read_log(d.recorder.path)
    assert np.all(log["u"] == 0.0) and np.all(log["enable"] == 0.0)


def test_missing_model_file_is_exit_2(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "truckd.cli.main", "run", "--config", str(default_config_path()),
         "--model", str(tmp_path / "missing.yaml"), "--duration", "1"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2
    assert "missing.yaml" in r.stderr


def test_a_failing_shutdown_step_still_closes_the_link_and_releases_the_device(
    tmp_path: Path,
) -> None:
    """A recorder that raises at shutdown (a bug, a dying disk) is logged; the motor-off
    before it went out and the link close and device release after it still happen."""
    cfg_path = write_config(
        tmp_path / "truck.yaml",
        {"runtime": {"realtime": False, "telemetry": {"enabled": False},
                     "recorder": {"dir": str(tmp_path / "logs")}}},
    )  # fmt: skip
    d = Daemon(load_config(cfg_path), "sim", duration=1.0, env={})
    closed: list[str] = []
    d.start()
    assert d.backend is not None and d.recorder is not None
    backend_close = d.backend.close

    def close_backend() -> None:
        closed.append("backend")
        backend_close()

    def recorder_stop() -> None:
        raise OSError("injected: the disk went away")

    d.backend.close = close_backend  # type: ignore[method-assign]
    d.recorder.stop = recorder_stop  # type: ignore[method-assign]
    if d.claim is not None:
        claim_release = d.claim.release

        def release() -> None:
            closed.append("claim")
            claim_release()

        d.claim.release = release  # type: ignore[method-assign]
    try:
        d.shutdown()
    finally:
        unfreeze_gc()
    assert "backend" in closed
    assert d.claim is None or "claim" in closed
    fw = d.backend.firmware
    assert fw is not None and (fw.voltage, fw.enabled) == (0.0, False)
