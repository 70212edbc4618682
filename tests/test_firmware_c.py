"""The C firmware core (firmware_protocol/firmware/) on the host, through the ctypes
binding, with a scripted HAL: schedule, command timeout (also across the 2^32 ms clock
wrap), receive checks against the Python reference (firmware_protocol.checks), garbage on
the serial line against the Python deframer, heartbeat fault bits, range and encoder
handling, and the fault hooks."""

from __future__ import annotations

import os
import random
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from firmware_protocol.checks import RESYNC, RxChecker
from firmware_protocol.codec import Frame, decode, encode, encode_raw
from firmware_protocol.crc import message_checksum
from firmware_protocol.framing import Deframer, frame_to_bytes
from firmware_protocol.fwcore import (
    RANGE_NO_TARGET,
    RANGE_SENSOR_FAULT,
    RANGE_VALID,
    TX_BAD_CHECKSUM,
    TX_FREEZE,
    TX_STUCK_COUNTER,
    CoreConfig,
    FirmwareCore,
)
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
)
from truckd.io.port import FIRMWARE_RX, companion_port
from truckd.model.params import VehicleParams
from truckd.sim.firmware import constant_speed_lead, simulated_truck
from truckd.sim.plant import Plant


@dataclass
class Hal:
    """Scripted hardware: sensor values to return, everything the core did."""

    ticks: int = 0
    enc_status: int = 0
    current_ma: int = 1500
    vbat_mv: int = 7200
    range_status: int = RANGE_VALID
    range_mm: int = 1234
    motor: list[tuple[int, int, bool]] = field(default_factory=list)  # (ms, mV, enable)
    wire: bytearray = field(default_factory=bytearray)
    frames: list[tuple[int, Frame]] = field(default_factory=list)  # (ms, frame)
    core: FirmwareCore | None = None
    raise_in_range: bool = False

    def read_encoders(self) -> tuple[int, int, int]:
        return self.ticks, self.ticks + 1, self.enc_status

    def read_power(self) -> tuple[int, int, int]:
        return self.current_ma, self.vbat_mv, self.motor[-1][1] if self.motor else 0

    def read_range(self) -> tuple[int, int]:
        if self.raise_in_range:
            raise RuntimeError("range sensor driver crashed")
        return self.range_status, self.range_mm

    def set_motor(self, voltage_mv: int, enable: bool) -> None:
        assert self.core is not None or not self.motor
        self.motor.append((self.core.now_ms if self.core else 0, voltage_mv, enable))

    def send_bytes(self, data: bytes) -> bool:
        self.wire += data
        return True

    def send_frame(self, can_id: int, data: bytes) -> bool:
        assert self.core is not None
        self.frames.append((self.core.now_ms, Frame(can_id, data)))
        return True


def make(link: str = "can", t0: int = 0, **cfg: int) -> tuple[FirmwareCore, Hal]:
    hal = Hal()
    core = FirmwareCore(hal, CoreConfig(link=link, **cfg), now_ms=t0)  # type: ignore[arg-type]
    hal.core = core
    return core, hal


def run_to(core: FirmwareCore, ms: int) -> None:
    """Poll every millisecond up to and including ``ms``."""
    while core.now_ms != ms & 0xFFFFFFFF:
        core.now_ms += 1
        core.poll()


def cmd(core: FirmwareCore, voltage: float, counter: int, enable: bool = True) -> None:
    f = encode(MotorCommand(voltage, enable), counter)
    core.rx_frame(f.can_id, f.data)


def sent(hal: Hal, name: str) -> list[tuple[int, object]]:
    out = []
    for ms, f in hal.frames:
        d = decode(f)  # raises unless id, length, CHECKSUM and ranges are right
        if d.name == name:
            out.append((ms, d.msg))
    return out


def test_every_message_at_its_period_with_counters_and_checksums() -> None:
    core, hal = make()
    core.poll()
    run_to(core, 1000)
    n = Counter(decode(f).name for _, f in hal.frames)
    assert n == {
        "WHEEL_ENCODERS": 101,
        "MOTOR_FEEDBACK": 101,
        "RANGE": 51,
        "FIRMWARE_HEARTBEAT": 11,
    }
    for name, period in (("WHEEL_ENCODERS", 10), ("RANGE", 20), ("FIRMWARE_HEARTBEAT", 100)):
        times = [ms for ms, f in hal.frames if decode(f).name == name]
        assert times == list(range(0, 1001, period))
        counters = [decode(f).counter for _, f in hal.frames if decode(f).name == name]
        assert counters == [k % 16 for k in range(len(counters))]
    enc = [m for _, m in sent(hal, "WHEEL_ENCODERS")]
    assert isinstance(enc[3], WheelEncoders)
    assert enc[3].sample_time == pytest.approx(0.03) and enc[3].ticks_right == 1
    fb = sent(hal, "MOTOR_FEEDBACK")[0][1]
    assert isinstance(fb, MotorFeedback) and fb.current == pytest.approx(1.5)
    assert fb.vbat == pytest.approx(7.2) and fb.status == 0
    assert core.stats()["fw"]["schedule_slips"] == 0


def test_late_poll_skips_missed_periods_and_keeps_the_phase() -> None:
    core, hal = make()
    core.poll()
    core.now_ms = 35  # three encoder periods missed
    core.poll()
    run_to(core, 60)
    times = [ms for ms, f in hal.frames if decode(f).name == "WHEEL_ENCODERS"]
    assert times == [0, 35, 40, 50, 60]
    # the 10, 20, 30 ms slots are served once at 35 ms: two skipped each for the encoders
    # and the feedback; RANGE (20 ms, due at 20) is late but skips nothing
    assert core.stats()["fw"]["schedule_slips"] == 2 + 2


@pytest.mark.parametrize("t0", [0, 2**32 - 250])  # also across the 32-bit clock wrap
@pytest.mark.parametrize("timeout_ms", [100, 37])
def test_motor_off_exactly_cmd_timeout_after_the_last_valid_command(
    t0: int, timeout_ms: int
) -> None:
    core, hal = make(t0=t0, cmd_timeout_ms=timeout_ms)
    core.poll()
    for k in range(50):  # a command every 10 ms, the last at t0 + 490
        core.now_ms = (t0 + 10 * k) & 0xFFFFFFFF
        cmd(core, 3.0, k)
        core.poll()
    last = (t0 + 490) & 0xFFFFFFFF
    assert core.state == FirmwareState.ACTIVE and core.voltage_mv == 3000
    assert core.next_event() in {(last + timeout_ms) & 0xFFFFFFFF, (last + 10) & 0xFFFFFFFF}
    run_to(core, last + timeout_ms - 1)
    assert core.enabled and core.voltage_mv == 3000
    run_to(core, last + timeout_ms)
    assert hal.motor[-1] == ((last + timeout_ms) & 0xFFFFFFFF, 0, False)
    assert core.state == FirmwareState.FAILSAFE
    assert core.stats()["fw"]["cmd_timeouts"] == 1
    run_to(core, last + 300)
    hb = [m for _, m in sent(hal, "FIRMWARE_HEARTBEAT")][-1]
    assert isinstance(hb, FirmwareHeartbeat)
    assert hb.state == FirmwareState.FAILSAFE and hb.faults & FirmwareFault.CMD_TIMEOUT
    # a valid command drives again; the timeout bit is gone after one heartbeat reported it
    for k in range(30):
        core.now_ms = (last + 301 + 10 * k) & 0xFFFFFFFF
        cmd(core, -2.0, (50 + k) % 16)
        core.poll()
    assert core.state == FirmwareState.ACTIVE and hal.motor[-1][1:] == (-2000, True)
    hb = [m for _, m in sent(hal, "FIRMWARE_HEARTBEAT")][-1]
    assert isinstance(hb, FirmwareHeartbeat) and not hb.faults & FirmwareFault.CMD_TIMEOUT


def test_never_commanded_motor_stays_off_and_reports_the_timeout() -> None:
    core, hal = make()
    core.poll()
    run_to(core, 99)
    assert not core.fault_bits() & FirmwareFault.CMD_TIMEOUT
    run_to(core, 200)
    assert hal.motor == [(0, 0, False)]
    assert core.state == FirmwareState.IDLE and core.fault_bits() & FirmwareFault.CMD_TIMEOUT


def test_disable_and_clamp_to_the_battery() -> None:
    core, hal = make()
    hal.vbat_mv = 7000
    cmd(core, 30.0, 0)
    assert hal.motor[-1] == (0, 7000, True) and core.last_command() == (30000, True)
    assert core.fault_bits() & FirmwareFault.CMD_INVALID
    cmd(core, -9.0, 1)
    assert hal.motor[-1][1] == -7000
    cmd(core, 3.0, 2, enable=False)
    assert hal.motor[-1] == (0, 0, False) and core.state == FirmwareState.IDLE
    assert core.last_command() == (3000, False)


def _frames_for_checks(rng: random.Random, n: int) -> list[tuple[int, Frame]]:
    """A command stream with every kind of trouble: counter repeats, jumps and random
    counters, wrong checksums, wrong lengths, unknown ids, out-of-range payloads, own
    messages echoed, and pauses beyond the freshness timeouts."""
    out = []
    t = 0
    c_cmd = c_hb = 0
    for _ in range(n):
        t += rng.choice([1, 5, 10, 10, 10, 60, 700]) if rng.random() < 0.2 else 10
        r = rng.random()
        if r < 0.55:
            c_cmd = (c_cmd + rng.choice([*[1] * 30, 0, 2, 3, 5, rng.randrange(16)])) % 16
            f = encode(MotorCommand(rng.uniform(-8, 8), rng.random() < 0.9), c_cmd)
        elif r < 0.7:
            c_hb = (c_hb + rng.choice([1, 1, 0, 3])) % 16
            f = encode(CompanionHeartbeat(CompanionState(rng.randrange(5)), 0), c_hb)
        elif r < 0.76:
            f = encode(MotorCommand(1.0, True), rng.randrange(16))
            f = Frame(f.can_id, f.data[:-1] + bytes((f.data[-1] ^ (1 << rng.randrange(8)),)))
        elif r < 0.8:
            f = Frame(0x100, bytes(rng.randrange(256) for _ in range(rng.choice([0, 3, 5, 8]))))
        elif r < 0.84:
            f = Frame(rng.choice([0x101, 0x7FF, 0x000]), bytes(4))
        elif r < 0.88:
            f = encode(MotorCommand(0.0, True), rng.randrange(16))  # VOLTAGE raw -32768
            body = b"\x00\x80" + f.data[2:-1]
            f = Frame(f.can_id, body + bytes((message_checksum(f.can_id, body),)))
        elif r < 0.92:
            f = encode_raw("COMPANION_HEARTBEAT", {"STATE": 9, "FAULTS": 0}, rng.randrange(16))
        else:
            f = encode(RangeReading(1.0, RangeStatus.VALID, 0.1), rng.randrange(16))
        out.append((t, f))
    return out


@pytest.mark.parametrize("seed", range(4))
def test_receive_checks_match_the_python_reference(seed: int) -> None:
    core, _ = make()
    # the reference runs on the same integer ms clock (timeouts 5 periods, in ms), so no
    # float rounding blurs the exact timeout boundary
    ref = RxChecker(expect=FIRMWARE_RX, timeout_periods=5000.0, resync=RESYNC)
    assert ref._state["MOTOR_CMD"].timeout == 50.0
    applied = 0
    for t, f in _frames_for_checks(random.Random(seed), 3000):
        core.now_ms = t
        core.rx_frame(f.can_id, f.data)
        d = ref.accept(f, float(t))
        if d is not None and d.name == "MOTOR_CMD":
            applied += 1
            assert isinstance(d.msg, MotorCommand)
            assert core.last_command() == (round(d.msg.voltage * 1000), d.msg.enable)
    ref.poll_timeouts(float(core.now_ms))
    core.rx_fresh("MOTOR_CMD")
    core.rx_fresh("COMPANION_HEARTBEAT")
    assert core.stats()["rx"] == ref.stats.as_dict()
    assert core.stats()["fw"]["commands_applied"] == applied > 100
    st = ref.stats
    errors = st.checksum_errors + st.length_errors + st.counter_errors + st.payload_errors
    assert core.cmd_errors == errors % 256


def test_bad_commands_are_not_applied_and_do_not_feed_the_timeout() -> None:
    core, hal = make()
    cmd(core, 3.0, 0)
    good = encode(MotorCommand(5.0, True), 1)
    bad = Frame(good.can_id, good.data[:-1] + bytes((good.data[-1] ^ 0x10,)))
    for k in range(1, 30):
        core.now_ms = 10 * k
        core.rx_frame(bad.can_id, bad.data)
        core.poll()
    assert hal.motor[1] == (0, 3000, True)  # the only command applied
    assert hal.motor[-1] == (100, 0, False) and core.state == FirmwareState.FAILSAFE
    hb = [m for _, m in sent(hal, "FIRMWARE_HEARTBEAT")]
    assert isinstance(hb[-1], FirmwareHeartbeat)
    # the heartbeat at 200 ms counted the bad frames of 10..200 ms
    assert hb[-1].faults & FirmwareFault.CMD_CHECKSUM and hb[-1].cmd_errors == 20
    assert core.cmd_errors == 29
    run_to(core, 400)  # no more bad frames: the event bit was reported, now it is gone
    hb = [m for _, m in sent(hal, "FIRMWARE_HEARTBEAT")]
    assert isinstance(hb[-1], FirmwareHeartbeat) and not hb[-1].faults & FirmwareFault.CMD_CHECKSUM
    # a repeated counter is rejected and reported as CMD_COUNTER
    cmd(core, 1.0, 5)
    cmd(core, 2.0, 5)
    assert core.last_command() == (1000, True)
    assert core.fault_bits() & FirmwareFault.CMD_COUNTER


@pytest.mark.parametrize("seed", range(3))
def test_garbage_bytes_on_the_serial_line(seed: int) -> None:
    """Random bytes between (and inside) framed commands: the C deframer counts what the
    Python one counts, and the C receive checks apply what the Python ones accept: every
    intact command but those after a run of three or more lost (a jump the replay rule
    refuses until 16 frames have run in sequence)."""
    rng = random.Random(seed)
    core, _ = make(link="serial")
    stream = bytearray()
    intact = 0
    for k in range(400):
        f = frame_to_bytes(encode(MotorCommand(rng.uniform(-5, 5), True), k % 16))
        r = rng.random()
        if r < 0.2:
            stream += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 40)))
        if r < 0.1:  # a frame cut short by garbage
            stream += f[: rng.randrange(1, len(f) - 1)]
            continue
        stream += f
        intact += 1
    ref = Deframer()
    frames = ref.feed(bytes(stream))
    pos = 0
    while pos < len(stream):  # arbitrary chunks, as a UART delivers them
        n = rng.randrange(1, 64)
        core.rx_bytes(bytes(stream[pos : pos + n]))
        pos += n
    assert core.stats()["framing"] == ref.stats.as_dict()
    assert len(frames) >= intact
    applied = core.stats()["fw"]["commands_applied"]
    checks = RxChecker(expect=FIRMWARE_RX, timeout_periods=5000.0, resync=RESYNC)
    accepted = [d for f in frames if (d := checks.accept(f, 0.0)) is not None]
    assert applied == core.stats()["rx"]["frames_ok"] == len(accepted)
    assert applied >= 0.8 * intact


def test_serial_output_is_the_python_framing() -> None:
    core, hal = make(link="serial")
    core.poll()
    frames = Deframer().feed(bytes(hal.wire))
    assert [decode(f).name for f in frames] == [
        "WHEEL_ENCODERS",
        "MOTOR_FEEDBACK",
        "RANGE",
        "FIRMWARE_HEARTBEAT",
    ]
    assert bytes(hal.wire) == b"".join(frame_to_bytes(f) for f in frames)


def test_heartbeat_fault_bits() -> None:
    core, hal = make()
    core.poll()
    assert core.fault_bits() & FirmwareFault.COMPANION_TIMEOUT  # never heard from it
    f = encode(CompanionHeartbeat(CompanionState.ACTIVE), 0)
    core.rx_frame(f.can_id, f.data)
    assert not core.fault_bits() & FirmwareFault.COMPANION_TIMEOUT
    core.now_ms = 500
    assert not core.fault_bits() & FirmwareFault.COMPANION_TIMEOUT
    core.now_ms = 501  # 5 periods of 100 ms
    assert core.fault_bits() & FirmwareFault.COMPANION_TIMEOUT
    hal.vbat_mv = 5499
    assert core.fault_bits() & FirmwareFault.UNDERVOLTAGE
    hal.vbat_mv = 5500
    assert not core.fault_bits() & FirmwareFault.UNDERVOLTAGE
    hal.enc_status = 2
    hal.range_status = RANGE_SENSOR_FAULT
    run_to(core, 600)
    bits = core.fault_bits()
    assert bits & FirmwareFault.ENCODER and bits & FirmwareFault.RANGE_SENSOR
    hal.enc_status = 0
    hal.range_status = RANGE_VALID
    run_to(core, 620)
    bits = core.fault_bits()
    assert not bits & (FirmwareFault.ENCODER | FirmwareFault.RANGE_SENSOR)


@pytest.mark.parametrize(
    ("status", "mm", "want_status", "want_m"),
    [
        (RANGE_VALID, 1234, RangeStatus.VALID, 1.234),
        (RANGE_VALID, 4000, RangeStatus.VALID, 4.0),
        (RANGE_VALID, 4001, RangeStatus.NO_TARGET, 0.0),
        (RANGE_VALID, 5, RangeStatus.VALID, 0.02),  # below the minimum: the minimum
        (RANGE_VALID, -300, RangeStatus.VALID, 0.02),
        (RANGE_NO_TARGET, 1000, RangeStatus.NO_TARGET, 0.0),
        (RANGE_SENSOR_FAULT, 1000, RangeStatus.SENSOR_FAULT, 0.0),
        (7, 1000, RangeStatus.SENSOR_FAULT, 0.0),  # a status the core does not know
    ],
)
def test_range_reading(status: int, mm: int, want_status: RangeStatus, want_m: float) -> None:
    core, hal = make()
    hal.range_status, hal.range_mm = status, mm
    core.poll()
    r = sent(hal, "RANGE")[0][1]
    assert isinstance(r, RangeReading)
    assert r.status == want_status and r.distance == pytest.approx(want_m)


def test_fault_hooks() -> None:
    core, hal = make()
    core.poll()
    core.set_tx_fault("RANGE", TX_BAD_CHECKSUM)
    core.set_tx_fault("WHEEL_ENCODERS", TX_STUCK_COUNTER | TX_FREEZE)
    core.set_drop("MOTOR_FEEDBACK", 2)
    hal.ticks = 77
    n0 = len(hal.frames)
    run_to(core, 40)
    new = [f for _, f in hal.frames[n0:]]
    rng = [f for f in new if f.can_id == 0x220]
    assert len(rng) == 2 and all(decode_fails(f) for f in rng)
    enc = [decode(f) for f in new if f.can_id == 0x200]
    assert [d.counter for d in enc] == [1, 1, 1, 1]
    assert all(isinstance(d.msg, WheelEncoders) and d.msg.ticks_left == 0 for d in enc)  # frozen
    assert sum(f.can_id == 0x210 for f in new) == 2  # 4 due, 2 dropped
    assert core.stats()["fw"]["frames_dropped"] == 2
    core.set_silent(True)
    n0 = len(hal.frames)
    run_to(core, 100)
    assert len(hal.frames) == n0
    core.clear_faults()
    run_to(core, 130)
    enc = [decode(f) for _, f in hal.frames[n0:] if f.can_id == 0x200]
    assert enc[-1].counter != enc[0].counter and enc[-1].msg.ticks_left == 77  # type: ignore[union-attr]
    with pytest.raises(ValueError):
        core.set_drop("RANGE", -2)


def decode_fails(f: Frame) -> bool:
    try:
        decode(f)
    except ValueError as exc:
        return "checksum" in str(exc)
    return False


def test_hal_exception_is_raised_after_the_c_call() -> None:
    core, hal = make()
    hal.raise_in_range = True
    with pytest.raises(RuntimeError, match="range sensor driver crashed"):
        core.poll()
    hal.raise_in_range = False
    core.now_ms = 20
    core.poll()  # the core carries on
    # meanwhile the failed read counted as a sensor fault; the next one is fine
    assert sent(hal, "RANGE")[0][1] == RangeReading(0.0, RangeStatus.SENSOR_FAULT, 0.0)
    assert sent(hal, "RANGE")[-1][1] == RangeReading(1.234, RangeStatus.VALID, 0.02)


def test_bad_configuration_refused() -> None:
    with pytest.raises(ValueError, match="cmd_timeout_ms"):
        make(cmd_timeout_ms=0)


def _in_fresh_process(env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    code = (
        "from firmware_protocol.fwcore import FirmwareCore, FirmwareBuildError\n"
        "from test_firmware_c import Hal\n"
        "try:\n"
        "    core = FirmwareCore(Hal())\n"
        "except FirmwareBuildError as exc:\n"
        "    raise SystemExit(f'build error: {exc}')\n"
        "core.poll()\n"
        "print(core.stats()['fw']['frames_sent'])\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        env=os.environ | {"PYTHONPATH": str(Path(__file__).parent)} | env,
        check=False,
    )


def test_library_is_built_on_first_use(tmp_path: Path) -> None:
    res = _in_fresh_process({"TRUCKD_FW_BUILD_DIR": str(tmp_path / "b")})
    assert res.returncode == 0 and res.stdout.strip() == "4", res.stderr
    assert (tmp_path / "b" / "libtruckfw.so").is_file()


def test_a_missing_library_is_a_clear_error(tmp_path: Path) -> None:
    res = _in_fresh_process({"TRUCKD_FW_LIB": str(tmp_path / "nope.so")})
    assert res.returncode == 1 and "build error: cannot load the C firmware core" in res.stderr


def test_the_simulated_truck_runs_the_c_core(params: VehicleParams) -> None:
    """One firmware behaviour: what truckd sim and the HIL processes drive is the C core."""
    plant = Plant(params)
    link, fw, _ = simulated_truck(plant, constant_speed_lead(2.0, 1.0), "bytes")
    port = companion_port(link, clock=lambda: fw.t)
    for _ in range(30):
        port.send(MotorCommand(2.5, True))
        fw.step(0.01)
        port.poll()
    assert isinstance(fw.core, FirmwareCore) and fw.core.config.link == "serial"
    core = fw.core.stats()
    assert core["fw"]["commands_applied"] == fw.stats.commands_applied == 30
    assert core["framing"]["frames_ok"] == 30  # the C deframer read the serial bytes
    assert fw.core.voltage_mv == 2500 and plant.v > 0.0


def test_build_dir_falls_back_to_tmp_without_a_writable_home(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A service user whose home cannot be written (systemd's DynamicUser, nobody with
    HOME=/root): the core is built in a directory of the user's under the temporary
    directory, not failed with a PermissionError."""
    import os
    import tempfile

    from firmware_protocol import fwcore

    monkeypatch.delenv("TRUCKD_FW_BUILD_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "home" / ".cache"))
    writable = {Path(tempfile.gettempdir())}
    monkeypatch.setattr(fwcore.os, "access", lambda p, _mode: Path(p) in writable)
    d = fwcore._build_dir()
    assert d == Path(tempfile.gettempdir()) / f"truckd-{os.getuid()}" / "firmware"
    writable.add(tmp_path)  # a home that can be created: its cache
    assert fwcore._build_dir() == tmp_path / "home" / ".cache" / "truckd" / "firmware"


def test_a_build_dir_under_tmp_that_others_may_write_is_refused(tmp_path: Path) -> None:
    from firmware_protocol import fwcore

    build = tmp_path / "shared" / "firmware"
    build.mkdir(parents=True)
    build.parent.chmod(0o777)  # as if another user had made it for us
    with pytest.raises(fwcore.FirmwareBuildError, match="others may write"):
        fwcore._own_dir_only(build)
    build.parent.chmod(0o700)
    fwcore._own_dir_only(build)  # ours alone: fine


def test_the_tmp_build_dir_is_private_whatever_the_umask(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Under umask 002 (Debian's default for users) mkdir's parents came out 0775 and the
    fallback refused its own directory; it is made 0700, checked, and the core builds."""
    import os
    import stat
    import tempfile

    from firmware_protocol import fwcore

    monkeypatch.delenv("TRUCKD_FW_BUILD_DIR", raising=False)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setenv("XDG_CACHE_HOME", "/proc/no-cache")  # not writable: the fallback
    real_access = os.access
    monkeypatch.setattr(
        fwcore.os,
        "access",
        lambda p, m: (
            False
            if str(p) == str(fwcore.FIRMWARE_DIR) or str(p).startswith("/proc")
            else real_access(p, m)
        ),
    )
    old = os.umask(0o002)
    try:
        lib = fwcore.build_library()
    finally:
        os.umask(old)
    assert lib.exists() and lib.parent == tmp_path / f"truckd-{os.getuid()}" / "firmware"
    for d in (lib.parent, lib.parent.parent):
        assert stat.S_IMODE(d.stat().st_mode) == 0o700


@pytest.mark.parametrize("loop", [(6, 7), (5, 6, 7), (2, 3, 4, 5, 6, 7), tuple(range(12))])
def test_a_replayed_loop_of_the_last_commands_does_not_keep_the_motor_driven(
    loop: tuple[int, ...],
) -> None:
    """The companion is gone and its last frames come round again and again (a gateway or
    a buffer replaying them): before, the loop 6, 7, 6, 7, ... was accepted and kept the
    motor at 5 V for as long as it went on.  Now the first backward jump is refused, and
    every frame after it until 16 have run in sequence: the command times out and the
    motor goes off.  A sender that resumes in sequence is accepted after 16 frames."""
    core, hal = make()
    frames = {k: encode(MotorCommand(5.0, True), k) for k in range(16)}
    t = 0
    for k in range(8):  # normal commands, counters 0..7
        t += 10
        core.now_ms = t
        core.rx_frame(frames[k].can_id, frames[k].data)
        core.poll()
    assert core.last_command() == (5000, True) and hal.motor[-1][2]
    for k in range(600):  # 6 s of the loop
        t += 10
        core.now_ms = t
        f = frames[loop[k % len(loop)]]
        core.rx_frame(f.can_id, f.data)
        core.poll()
        if t > 80 + 200:
            assert not hal.motor[-1][2], (t, hal.motor[-1])  # off, and stays off
    assert core.state == FirmwareState.FAILSAFE
    # the companion back, in sequence: commands again after the run
    for k in range(40):
        t += 10
        core.now_ms = t
        f = frames[(loop[-1] + 1 + k) % 16]
        core.rx_frame(f.can_id, f.data)
        core.poll()
    assert hal.motor[-1][2] and hal.motor[-1][1] == 5000


def test_python_checks_refuse_the_replayed_loop_on_the_motor_side_only() -> None:
    """The same rule in the Python reference (the firmware's receive), and not on the
    companion's receive of sensor data, where a burst of lost frames must not blind it."""
    frames = [encode(MotorCommand(1.0, True), k % 16) for k in range(8)]
    loop = [encode(MotorCommand(1.0, True), k) for k in (6, 7)] * 20
    strict = RxChecker(expect=FIRMWARE_RX, resync=RESYNC)
    tolerant = RxChecker(expect=FIRMWARE_RX)
    for k, f in enumerate(frames + loop):
        now = 0.01 * k
        a = strict.accept(f, now)
        tolerant.accept(f, now)
        if k >= len(frames):
            assert a is None
    assert tolerant.stats.frames_ok > len(frames) + 10  # the old rule let the loop in


def test_an_event_fault_bit_waits_for_a_heartbeat_that_is_sent() -> None:
    """A CMD_CHECKSUM event, then a heartbeat the HAL could not send: the next heartbeat
    that goes out still reports it (the bits were cleared when the heartbeat was built)."""
    core, hal = make()
    run_to(core, 150)
    good = encode(MotorCommand(1.0, True), 1)
    core.rx_frame(good.can_id, good.data[:-1] + bytes((good.data[-1] ^ 0x10,)))  # bad CRC
    fail = {"on": True}
    real = hal.send_frame

    def flaky(can_id: int, data: bytes) -> bool:
        if fail["on"] and decode(Frame(can_id, data)).name == "FIRMWARE_HEARTBEAT":
            fail["on"] = False
            return False  # this heartbeat is lost
        return real(can_id, data)

    hal.send_frame = flaky  # type: ignore[method-assign]
    run_to(core, 450)
    beats = [m for ms, m in sent(hal, "FIRMWARE_HEARTBEAT") if ms > 150]
    assert beats and isinstance(beats[0], FirmwareHeartbeat)
    assert beats[0].faults & FirmwareFault.CMD_CHECKSUM


def test_extreme_current_and_a_month_without_commands() -> None:
    """A current at the int32 ends saturates the right way (an overflow, undefined
    behaviour, made INT32_MAX read -32768); CMD_TIMEOUT before any command stays set past
    2^31 ms (the elapsed time since start wrapped after 24.9 days)."""
    core, hal = make()
    for ma, want in ((2**31 - 1, 327.67), (-(2**31), -327.68)):
        hal.current_ma = ma
        core.now_ms += 100
        core.poll()
        fb = sent(hal, "MOTOR_FEEDBACK")[-1][1]
        assert isinstance(fb, MotorFeedback) and fb.current == pytest.approx(want)
    for now in (1000, 2**31 - 1, 2**31 + 20, 2**32 - 10):
        core.now_ms = now
        core.poll()
        assert core.fault_bits() & FirmwareFault.CMD_TIMEOUT, now
