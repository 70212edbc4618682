"""A motor commanded that does not turn, in the closed loop: the supervisor stops it."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import yaml
from runtime_support import deep_merge

from truckd.cli.main import main
from truckd.config.truck import default_config_path


def test_a_truck_that_cannot_break_away_is_stopped_and_retried(tmp_path: Path) -> None:
    """A simulated truck with ten times the winding resistance its controller believes
    (its stall torque below its stiction at the voltage the controller sends) stood at
    3.9 V for the whole 15 s cruise (mode DEGRADED). Now the stall is stopped after
    ``stall_s`` and retried after the cool-down: the motor pushes 4.5 s of 15."""
    base = yaml.safe_load(default_config_path().read_text())
    over = {"plant": {"vehicle": {"R_m": 10.0 * base["vehicle"]["R_m"]}}}
    cfg = tmp_path / "weak.yaml"
    cfg.write_text(yaml.safe_dump(deep_merge(base, over)))
    out, traces = tmp_path / "cruise.json", tmp_path / "traces"
    args = ["sim", "--config", str(cfg), "--scenario", "cruise"]
    assert main([*args, "--json", str(out), "--trace", str(traces)]) == 0
    row = json.loads(out.read_text())
    row = row[0] if isinstance(row, list) else row
    assert row["final_speed_m_s"] < 0.05  # it cannot move: physics
    assert row["mode_time_s"]["SAFE_STOP"] > 5.0
    with (traces / "cruise.csv").open() as f:
        rows = list(csv.DictReader(f))
    sup = base["runtime"]["supervisor"]
    dt = float(rows[1]["t"]) - float(rows[0]["t"])
    pushing_s = dt * sum(
        1
        for r in rows
        if abs(float(r["u"])) >= sup["stall_command_v"] and abs(float(r["v_true"])) < 0.05
    )
    # one stall time per stall time + cool-down + recovery that the run began
    period = sup["stall_s"] + sup["stall_cooldown_s"] + sup["recovery_s"]
    windows = math.ceil(row["duration_s"] / period)
    assert sup["stall_s"] <= pushing_s <= windows * sup["stall_s"] + 0.1


def _lead_brake(tmp_path: Path, over: dict[str, object]) -> dict[str, object]:
    base = yaml.safe_load(default_config_path().read_text())
    tmp_path.mkdir()
    cfg = tmp_path / "truck.yaml"
    cfg.write_text(yaml.safe_dump(deep_merge(base, over)))
    out = tmp_path / "lead-brake.json"
    args = ["sim", "--config", str(cfg), "--scenario", "lead-brake", "--json", str(out)]
    assert main(args) == 0
    row = json.loads(out.read_text())
    return dict(row[0] if isinstance(row, list) else row)


def test_the_time_below_the_minimum_gap_is_reported(tmp_path: Path) -> None:
    """``control.d_min`` is a soft constraint: a simulated truck ten times heavier than its
    controller's model went to 0.148 m against 0.15 in lead-brake, and the JSON said
    nothing of it. ``time_below_d_min_s`` counts it; the configured truck keeps it 0."""
    heavy = _lead_brake(tmp_path / "heavy", {"plant": {"vehicle": {"m": 35.0, "J_S": 1.6e-4}}})
    d_min = yaml.safe_load(default_config_path().read_text())["control"]["d_min"]
    assert float(heavy["min_gap_m"]) < d_min  # type: ignore[arg-type]
    assert float(heavy["time_below_d_min_s"]) > 0.0  # type: ignore[arg-type]
    clean = _lead_brake(tmp_path / "clean", {})
    assert float(clean["min_gap_m"]) > d_min  # type: ignore[arg-type]
    assert clean["time_below_d_min_s"] == 0.0
