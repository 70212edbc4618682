"""Pairs of keys that pass one by one but cannot work together are refused when the
configuration loads, with one line naming both keys (exit 2 on the command line), whatever
command loads it."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pytest
import yaml
from cli_support import bad_input
from runtime_support import deep_merge

from firmware_protocol.timing import timing
from truckd.config.cross import cross_section_problem
from truckd.config.truck import default_config_path, load_config, parse_config
from truckd.errors import InputError


def _text(overrides: Mapping[str, Any]) -> str:
    base = yaml.safe_load(default_config_path().read_text())
    return yaml.safe_dump(deep_merge(base, overrides))


LIGHT = {"J_S": 1.6e-6, "m": 0.35}
"""A truck with a tenth of the default's mass and inertia."""


REFUSED: list[tuple[dict[str, Any], str]] = [
    (
        {"control": {"rate_hz": 8.0}},
        "key 'control.rate_hz' = 8: expected at least 20 Hz, 2 motor commands within the "
        "firmware's command timeout (truck.dbc MOTOR_CMD TruckTimeoutTime 100 ms), else it "
        "switches the motor off between commands",
    ),
    (
        {"control": {"rate_hz": 19.5}, "runtime": {"stall_limit_s": 0.2}},
        "key 'control.rate_hz' = 19.5: expected at least 20 Hz, 2 motor commands within the "
        "firmware's command timeout (truck.dbc MOTOR_CMD TruckTimeoutTime 100 ms), else it "
        "switches the motor off between commands",
    ),
    (
        {"runtime": {"stall_limit_s": 0.015}},
        "key 'runtime.stall_limit_s' = 0.015: expected at least two control periods "
        "(0.02 s at control.rate_hz 100)",
    ),
    (
        {"control": {"rate_hz": 250.0}},
        "key 'control.time_budget_s' = 0.004: expected below the control period (0.004 s at "
        "control.rate_hz 250), else a solve that uses its budget overruns the cycle",
    ),
    (
        {"platoon": {"plan_timeout_s": 0.015}},
        "key 'platoon.plan_timeout_s' = 0.015: expected at least two control periods (0.02 s "
        "at control.rate_hz 100): a plan comes once a cycle",
    ),
    (
        {"runtime": {"supervisor": {"encoder_timeout_s": 0.015}}},
        "key 'runtime.supervisor.encoder_timeout_s' = 0.015: expected at least 0.02 s, two "
        "periods of WHEEL_ENCODERS (truck.dbc GenMsgCycleTime 10 ms)",
    ),
    (
        {"runtime": {"supervisor": {"range_timeout_s": 0.03}}},
        "key 'runtime.supervisor.range_timeout_s' = 0.03: expected at least 0.04 s, two "
        "periods of RANGE (truck.dbc GenMsgCycleTime 20 ms)",
    ),
    (
        {"control": {"estimator": {"encoder_timeout_s": 0.012}}},
        "key 'control.estimator.encoder_timeout_s' = 0.012: expected at least 0.02 s, two "
        "periods of WHEEL_ENCODERS (truck.dbc GenMsgCycleTime 10 ms)",
    ),
    (
        {"control": {"estimator": {"lead_timeout_s": 0.025}}},
        "key 'control.estimator.lead_timeout_s' = 0.025: expected at least 0.04 s, two "
        "periods of RANGE (truck.dbc GenMsgCycleTime 20 ms)",
    ),
    (
        {"runtime": {"supervisor": {"link_timeout_s": 0.01}}},
        "key 'runtime.supervisor.link_timeout_s' = 0.01: expected at least 0.02 s, two "
        "periods of the most frequent message (truck.dbc GenMsgCycleTime 10 ms)",
    ),
    (
        {"control": {"estimator": {"range_max": 70.0}}},
        "key 'control.estimator.range_max' = 70: expected at most 65.535 m, the largest "
        "distance RANGE.DISTANCE carries (truck.dbc)",
    ),
    (
        {"control": {"estimator": {"range_max": 1.5}}},
        "key 'control.estimator.range_max' = 1.5: expected above the gap kept at the speed "
        "limit, control.d_0 + control.time_headway x control.v_max = 0.4 + 0.6 x 2.4 = 1.84 m, "
        "else the lead leaves the sensor's range while followed",
    ),
    (
        {"platoon": {"predecessor": "truck0"}, "control": {"estimator": {"range_max": 3.0}}},
        "key 'control.estimator.range_max' = 3: expected above the gap kept at the speed "
        "limit, control.d_0 + platoon.acc_headway x control.v_max = 0.4 + 1.1 x 2.4 = 3.04 m, "
        "else the lead leaves the sensor's range while followed",
    ),
    (
        {"platoon": {"order": "auto"}, "control": {"estimator": {"range_max": 3.0}}},
        "key 'control.estimator.range_max' = 3: expected above the gap kept at the speed "
        "limit, control.d_0 + platoon.acc_headway x control.v_max = 0.4 + 1.1 x 2.4 = 3.04 m, "
        "else the lead leaves the sensor's range while followed",
    ),
    (
        {"control": {"estimator": {"range_min": 0.15}}},
        "key 'control.estimator.range_min' = 0.15: expected below control.d_min (0.15 m): the "
        "sensor must see the minimum gap",
    ),
    (
        {"control": {"estimator": {"ticks_modulo": 4096}}},
        "key 'control.estimator.ticks_modulo' = 4096: expected 65536, the wrap of "
        "WHEEL_ENCODERS.TICKS_LEFT (truck.dbc)",
    ),
    (
        {"control": {"estimator": {"sample_time_modulo": 6.5535}}},
        "key 'control.estimator.sample_time_modulo' = 6.5535: expected 6.5536 s, the wrap of "
        "WHEEL_ENCODERS.SAMPLE_TIME (truck.dbc)",
    ),
    (
        {"control": {"u_max": 3.5}},
        "key 'characterize.check_max_v' = 4: expected at most control.u_max (3.5 V): the "
        "command is clipped there",
    ),
    (
        {"vehicle": {"K_stiction": 0.5}},
        "vehicle.K_stiction = 0.5 N m: at least the stall torque at control.u_max "
        "(0.242012 N m, K_T u_max / R_m): the truck cannot move",
    ),
    (
        {"plant": {"vehicle": {"K_stiction": 0.3}}},
        "plant.vehicle.K_stiction = 0.3 N m: at least the stall torque at control.u_max "
        "(0.242012 N m, K_T u_max / R_m): the truck cannot move",
    ),
    (
        {"characterize": {"step_voltages": [1.5, 8.0]}},
        "key 'characterize.step_voltages[1]' = 8: expected at most control.u_max (7.2 V): the "
        "command is clipped there",
    ),
]


@pytest.mark.parametrize(("overrides", "line"), REFUSED, ids=[r[1][5:40] for r in REFUSED])
def test_a_combination_that_cannot_work_is_refused_with_one_line(
    overrides: dict[str, Any], line: str
) -> None:
    with pytest.raises(InputError) as err:
        parse_config(_text(overrides), "t.yaml")
    assert str(err.value) == f"t.yaml: {line}"


ACCEPTED: list[dict[str, Any]] = [
    {},
    {"vehicle": LIGHT},  # a light truck (a tenth of the mass and inertia) loads
    # the edges of the rules above, on the side that works
    {"control": {"rate_hz": 20.0}, "runtime": {"stall_limit_s": 0.1}},
    {"control": {"rate_hz": 249.0}},
    {"control": {"estimator": {"range_max": 1.85}}},
    {"platoon": {"predecessor": "truck0"}, "control": {"estimator": {"range_max": 3.05}}},
    {"control": {"u_max": 4.0, "estimator": {"range_min": 0.149}}, "characterize": {
        "step_voltages": [1.5, 4.0], "validation_v": 4.0}},
]  # fmt: skip


@pytest.mark.parametrize("overrides", ACCEPTED)
def test_combinations_that_work_load(overrides: dict[str, Any]) -> None:
    parse_config(_text(overrides), "t.yaml")


def test_the_heartbeat_rule_follows_the_dbc_period() -> None:
    """The heartbeat's period binds only after the command timeout (100 ms: at least 20 Hz
    is more than the 10 Hz heartbeat); with a protocol whose heartbeat is faster than the
    loop, the rate is refused naming it."""
    cfg = dataclasses.replace(
        load_config(),
        control=dataclasses.replace(load_config().control, rate_hz=40.0),
    )
    assert cross_section_problem(cfg) is None
    t = timing()
    fast = dataclasses.replace(
        t,
        periods={**t.periods, "COMPANION_HEARTBEAT": 0.02},
        timeouts={**t.timeouts, "MOTOR_CMD": 1.0},
    )
    assert cross_section_problem(cfg, fast) == (
        "key 'control.rate_hz' = 40: expected at least 50 Hz, the companion heartbeat's rate "
        "(truck.dbc COMPANION_HEARTBEAT GenMsgCycleTime 20 ms): the control cycle sends it"
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["sim", "--scenario", "follow"],
        ["sim", "--platoon", "3", "--scenario", "platoon-brake"],
        ["run", "--backend", "sim", "--duration", "1"],
        ["characterize", "--backend", "sim"],
        ["params", "--json"],
    ],
    ids=lambda a: " ".join(a[:2]),
)
def test_every_command_refuses_it_with_exit_2(
    argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The follow scenario at 8 Hz ran to exit 0 with 0 V applied in every cycle."""
    f = tmp_path / "slow.yaml"
    f.write_text(_text({"control": {"rate_hz": 8.0}}))
    line = bad_input([argv[0], "--config", str(f), *argv[1:]], capsys)
    assert f"{f}: key 'control.rate_hz' = 8: expected at least 20 Hz" in line
    assert "TruckTimeoutTime 100 ms" in line


def test_a_controller_model_that_cannot_move_is_refused(tmp_path: Path) -> None:
    """A model file (``run``/``sim --model``) whose stiction exceeds the stall torque at
    ``control.u_max`` is held to the same rule as the configured truck."""
    from truckd.modelfile import ModelFile, read_controller_model, write_model

    low = {"control": {"u_max": 4.0}, "characterize": {"step_voltages": [1.5, 4.0],
           "validation_v": 4.0}}  # fmt: skip
    cfg = parse_config(_text(low), "low.yaml")
    p = cfg.vehicle
    path = tmp_path / "stuck.yaml"
    # breaks away at 5 V: a model the battery (7.2 V) moves, the 4 V limit does not
    write_model(path, ModelFile(vehicle=p.replace(K_stiction=5.0 * p.K_T / p.R_m)))
    with pytest.raises(InputError, match=r"stuck.yaml: vehicle.K_stiction = .* cannot move"):
        read_controller_model(cfg, path)
    write_model(path, ModelFile(vehicle=p))
    assert read_controller_model(cfg, path).vehicle == p
