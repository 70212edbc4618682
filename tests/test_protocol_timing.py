"""Protocol timing has one source, truck.dbc: the Python receive checks, the companion's
heartbeat, the simulated firmware and the C firmware (through the generated
``c/truck_timing.h``) all take periods, the command timeout and the counter limits from it."""

from __future__ import annotations

import ctypes
import re
from pathlib import Path

import cantools

from firmware_protocol import checks, fwcore, generate
from firmware_protocol.codec import DBC_PATH, encode
from firmware_protocol.messages import MotorCommand
from firmware_protocol.timing import c_header, limits, limits_of, timing, timing_of
from truckd.runtime.cycle import HEARTBEAT_PERIOD_S
from truckd.sim.firmware import FirmwareSimConfig


def _defines(text: str) -> dict[str, int]:
    return {m[1]: int(m[2]) for m in re.finditer(r"#define (TRUCK_\w+) \((\d+)u?\)", text)}


def test_the_timing_is_what_the_dbc_declares() -> None:
    """Read independently of firmware_protocol.timing: the raw DBC text."""
    text = DBC_PATH.read_text(encoding="utf-8")
    ids = {int(m[1]): m[2] for m in re.finditer(r"^BO_ (\d+) (\w+):", text, re.M)}
    cycle = {
        ids[int(m[1])]: int(m[2]) / 1000.0
        for m in re.finditer(r'^BA_ "GenMsgCycleTime" BO_ (\d+) (\d+);', text, re.M)
    }
    t = timing()
    assert dict(t.periods) == cycle
    m = re.search(r'^BA_ "TruckTimeoutTime" BO_ 256 (\d+);', text, re.M)
    assert m is not None and t.cmd_timeout == int(m[1]) / 1000.0
    widths = {int(w) for w in re.findall(r"SG_ COUNTER : \d+\|(\d+)@", text)}
    assert widths == {t.counter_bits} and t.counter_modulo == 1 << t.counter_bits
    for attr, value in (
        ("TruckCounterMaxDelta", t.counter_max_delta),
        ("TruckCounterResync", t.counter_resync),
        ("TruckCounterMaxWrong", t.counter_max_wrong),
        ("TruckFreshnessPeriods", t.freshness_periods),
    ):
        m = re.search(rf'^BA_ "{attr}" (\d+);', text, re.M)
        assert m is not None and int(m[1]) == value, attr


def test_python_takes_the_dbc_timing() -> None:
    t = timing()
    assert (checks.MAX_DELTA, checks.RESYNC) == (t.counter_max_delta, t.counter_resync)
    assert checks.COUNTER_MODULO == t.counter_modulo
    rx = checks.RxChecker(expect=("MOTOR_CMD",))
    assert (rx.timeout_periods, rx.max_wrong_counters) == (
        t.freshness_periods,
        t.counter_max_wrong,
    )
    assert HEARTBEAT_PERIOD_S == t.heartbeat_period == t.periods["COMPANION_HEARTBEAT"]
    assert FirmwareSimConfig().cmd_timeout == t.cmd_timeout
    core = fwcore.CoreConfig()
    assert core.cmd_timeout_ms == round(t.cmd_timeout * 1000)
    assert (core.timeout_periods, core.max_wrong_counters) == (
        t.freshness_periods,
        t.counter_max_wrong,
    )
    # the encoder wraps the counter at the DBC's width
    wrapped = encode(MotorCommand(0.0, False), t.counter_modulo + 1)
    assert wrapped == encode(MotorCommand(0.0, False), 1)


def test_the_c_firmware_takes_the_dbc_timing() -> None:
    """The generated header is in sync, and the compiled firmware's own default
    configuration (truck_fw_default_config, C) equals the DBC's."""
    assert generate.out_of_sync() == []
    t = timing()
    d = _defines((generate.C_DIR / "truck_timing.h").read_text(encoding="utf-8"))
    assert d["TRUCK_MOTOR_CMD_TIMEOUT_MS"] == round(t.cmd_timeout * 1000)
    assert d["TRUCK_COUNTER_MODULO"] == t.counter_modulo
    assert d["TRUCK_COUNTER_MASK"] == t.counter_modulo - 1
    assert d["TRUCK_COUNTER_MAX_DELTA"] == t.counter_max_delta
    assert d["TRUCK_COUNTER_RESYNC"] == t.counter_resync
    lib = fwcore.load_library()
    cfg = fwcore._Config()
    lib.truck_fw_default_config(ctypes.byref(cfg))
    assert cfg.cmd_timeout_ms == round(t.cmd_timeout * 1000)
    assert (cfg.timeout_periods, cfg.max_wrong_counters) == (
        t.freshness_periods,
        t.counter_max_wrong,
    )
    # the default limits too: the same in C, in CoreConfig and in the simulated firmware
    lim = limits()
    mm = (round(lim.undervoltage * 1000), round(lim.range_min * 1000), round(lim.range_max * 1000))
    assert (d["TRUCK_UNDERVOLTAGE_MV"], d["TRUCK_RANGE_MIN_MM"], d["TRUCK_RANGE_MAX_MM"]) == mm
    assert (cfg.undervoltage_mv, cfg.range_min_mm, cfg.range_max_mm) == mm
    core = fwcore.CoreConfig()
    assert (core.undervoltage_mv, core.range_min_mm, core.range_max_mm) == mm
    sim = FirmwareSimConfig()
    assert (sim.undervoltage, sim.range_min, sim.range_max) == (
        lim.undervoltage,
        lim.range_min,
        lim.range_max,
    )
    # no counter arithmetic in the firmware core by a hand-written mask
    src = (fwcore.FIRMWARE_DIR / "truck_fw.c").read_text(encoding="utf-8")
    assert not re.search(r"counter\w*\s*[-+]?[^;]*&\s*0x[fF]u", src)
    assert "TRUCK_COUNTER_MASK" in src


def test_a_changed_dbc_changes_the_generated_c(tmp_path: Path) -> None:
    """The check can fail: another timeout and counter rule in the DBC give another header."""
    text = DBC_PATH.read_text(encoding="utf-8")
    text = text.replace(
        'BA_ "TruckTimeoutTime" BO_ 256 100;', 'BA_ "TruckTimeoutTime" BO_ 256 150;'
    )
    text = text.replace('BA_ "TruckCounterMaxDelta" 3;', 'BA_ "TruckCounterMaxDelta" 2;')
    text = text.replace('BA_ "TruckRangeMaxMm" 4000;', 'BA_ "TruckRangeMaxMm" 2500;')
    other = tmp_path / "other.dbc"
    other.write_text(text, encoding="utf-8")
    db = cantools.database.load_file(str(other), strict=True)
    t, lim = timing_of(db), limits_of(db)
    assert (t.cmd_timeout, t.counter_max_delta, lim.range_max) == (0.15, 2, 2.5)
    d = _defines(c_header(t, lim))
    assert (d["TRUCK_MOTOR_CMD_TIMEOUT_MS"], d["TRUCK_COUNTER_MAX_DELTA"]) == (150, 2)
    assert d["TRUCK_RANGE_MAX_MM"] == 2500
    assert c_header(t, lim) != (generate.C_DIR / "truck_timing.h").read_text(encoding="utf-8")
