"""Configuration validation: bad files are rejected whole, naming the key."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from truckd.config.truck import default_config_path, load_config, parse_config
from truckd.errors import InputError

GOOD = yaml.safe_load(default_config_path().read_text())


def mutate(path: str, value: object) -> str:
    data = yaml.safe_load(default_config_path().read_text())
    *parents, last = path.split(".")
    node = data
    for k in parents:
        node = node[k]
    if value is KeyError:
        del node[last]
    else:
        node[last] = value
    return yaml.safe_dump(data)


BAD = [
    ("vehicle.R_m", KeyError, "missing key 'vehicle.R_m'"),
    ("vehicle.R_m", -0.1, "'vehicle.R_m' = -0.1"),
    ("vehicle.R_m", 0.0, "'vehicle.R_m' = 0.0"),
    ("vehicle.K_T", "0.003", "'vehicle.K_T'"),
    ("vehicle.J_S", float("nan"), "'vehicle.J_S'"),
    ("vehicle.m", float("nan"), "expected a finite number in (0.0, 10000.0] kg"),
    ("vehicle.m", True, "'vehicle.m'"),
    ("vehicle.K_stiction", 0.001, "K_stiction"),
    ("vehicle.Kv", 0.1, "unknown key 'vehicle.Kv'"),
    ("vehicle", [1, 2], "'vehicle'"),
    ("plant.effects.input_delay", -0.01, "'plant.effects.input_delay'"),
    ("plant.effects.battery_sag", 20.0, "'plant.effects.battery_sag' = 20.0"),
    ("plant.effects.wind", 1.0, "unknown key 'plant.effects.wind'"),
    ("plant.effects.current_limit", -1.0, "'plant.effects.current_limit'"),
    ("plant.effects.backlash", 200.0, "'plant.effects.backlash' = 200.0"),
    ("plant.effects.rotor_inertia_fraction", 1.0, "'plant.effects.rotor_inertia_fraction'"),
    ("plant.effects.stribeck_speed", 0.0, "'plant.effects.stribeck_speed'"),
    ("plant.effects.winding_time_constant", 0.0, "'plant.effects.winding_time_constant'"),
    ("plant.encoder_ticks_per_rev", 12.5, "'plant.encoder_ticks_per_rev'"),
    ("vehicle_id", 7, "'vehicle_id'"),
    ("plant.vehicle", {"m": -1.0}, "'plant.vehicle.m' = -1.0"),
    ("plant.vehicle", {"K_v": 0.0}, "'plant.vehicle.K_v' = 0.0"),
    ("plant.vehicle", {"mass": 7.0}, "unknown key 'plant.vehicle.mass'"),
    ("plant.vehicle", {"K_stiction": 0.001}, "plant.vehicle: the simulated truck is not physical"),
    ("plant.wiring.motor_sign", 0, "motor_sign must be 1 or -1"),
    ("plant.wiring.encoder_sign", 2, "'plant.wiring.encoder_sign' = 2"),
    ("plant.wiring.counts_scale", 0.0, "'plant.wiring.counts_scale' = 0.0"),
    ("characterize.battery_min_v", 10.0, "battery_max_v (9.0) must be above battery_min_v"),
    ("characterize.step_voltages", [], "step_voltages must list at least one"),
    ("characterize.step_voltages", [1.0, -2.0], "'characterize.step_voltages[1]' = -2.0"),
    ("characterize.closed_loop_scenarios", ["platoon-brake"], "closed_loop_scenarios[0]'"),
    ("characterize.min_budget_m", 5.0, "min_budget_m (5.0) must not exceed track_length_m"),
    ("characterize.ramp", 1.0, "unknown key 'characterize.ramp'"),
    ("extra_section", {}, "unknown key 'extra_section'"),
    ("platoon.predecessor", "truck1", "the truck's own vehicle_id"),
    ("platoon.predecessor", "a b", "key 'platoon.predecessor' = 'a b'"),
    ("platoon.predecessor", "*", "key 'platoon.predecessor' = '*'"),
    ("control.u_max", 24.0, "expected at most vehicle.V_batt"),
    ("control.horizon", 300, "'control.horizon' = 300"),
    ("runtime.recorder.flush_period_s", 1e10, "'runtime.recorder.flush_period_s'"),
    ("runtime.telemetry.queue_size", 10**30, "'runtime.telemetry.queue_size'"),
    ("runtime.supervisor.range_timeout_s", 1e9, "'runtime.supervisor.range_timeout_s'"),
    ("runtime.supervisor.solver_fail_limit", 10**9, "'runtime.supervisor.solver_fail_limit'"),
]


def test_shipped_default_loads() -> None:
    cfg = load_config()
    assert cfg.vehicle_id == "truck1"
    assert cfg.vehicle.K_stiction >= cfg.vehicle.K_coulomb > 0


@pytest.mark.parametrize(("key", "value", "expected"), BAD)
def test_bad_file_is_rejected_naming_the_key(
    tmp_path: Path, key: str, value: object, expected: str
) -> None:
    f = tmp_path / "truck.yaml"
    f.write_text(mutate(key, value))
    with pytest.raises(InputError) as err:
        load_config(f)
    msg = str(err.value)
    assert expected in msg
    assert str(f) in msg
    assert "\n" not in msg


def test_range_message_says_what_is_allowed(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"expected a number in \(0.0, 100.0\] ohm"):
        parse_config(mutate("vehicle.R_m", -1.0), "t.yaml")


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file; expected a configuration file"):
        load_config(tmp_path / "absent.yaml")
    f = tmp_path / "broken.yaml"
    f.write_text("vehicle:\n  R_m: [1,\n")
    with pytest.raises(InputError, match=r"broken\.yaml:3:1: invalid YAML"):
        load_config(f)


def test_optional_sections_take_their_defaults() -> None:
    cfg = parse_config(yaml.safe_dump({"vehicle": GOOD["vehicle"]}), "minimal.yaml")
    assert cfg.plant.effects.active() == ()


def test_plant_vehicle_takes_any_subset_of_the_vehicle_keys() -> None:
    data = yaml.safe_load(default_config_path().read_text())
    data["plant"]["vehicle"] = {"m": 10.5, "K_v": 0.009}
    cfg = parse_config(yaml.safe_dump(data), "t.yaml")
    p = cfg.plant_vehicle
    assert (p.m, p.K_v) == (10.5, 0.009)
    assert cfg.vehicle.m == GOOD["vehicle"]["m"]  # the controller's truck is unchanged
    others = [k for k in GOOD["vehicle"] if k not in ("m", "K_v")]
    assert all(getattr(p, k) == getattr(cfg.vehicle, k) for k in others)
    assert load_config().plant_vehicle == load_config().vehicle  # none given: the same truck


def test_the_configuration_imports_nothing_of_the_runtime() -> None:
    """config is below runtime: loading the configuration (every section, the runtime's and
    characterize's included) loads no truckd.runtime module (the runtime imports config)."""
    import json
    import subprocess
    import sys

    probe = (
        "import json, sys\nimport truckd.config.truck\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.startswith('truckd.'))))"
    )
    r = subprocess.run(
        [sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True
    )
    loaded = set(json.loads(r.stdout))
    assert "truckd.config.runtime" in loaded and "truckd.config.characterize" in loaded
    assert not {m for m in loaded if m.startswith("truckd.runtime")}


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("  horizon: 40", "  horizon: 040", "'040' has a leading zero"),
        ("  m: 3.5", "  m: 3:30", "'3:30' is a base-60 number"),
        ("  horizon: 40", "  horizon: -040", "expected -40"),
        ("  horizon: 40", "  horizon: 0b101", "'0b101' is a binary number"),
    ],
)
def test_numbers_yaml_versions_read_differently_are_refused(
    old: str, new: str, expected: str
) -> None:
    """``040`` is 32 to YAML 1.1 (PyYAML) and 40 to YAML 1.2, ``3:30`` is 210 or text: a
    key that silently took the other value would drive another truck."""
    text = default_config_path().read_text(encoding="utf-8")
    assert old in text
    with pytest.raises(InputError, match=expected):
        parse_config(text.replace(old, new, 1), "t.yaml")


def test_a_date_like_value_is_text_as_in_yaml_1_2() -> None:
    """``vehicle_id: 2026-01-01`` is that name (YAML 1.1 would make it a date, refused
    with its Python repr)."""
    text = default_config_path().read_text(encoding="utf-8")
    assert "vehicle_id: truck1" in text
    cfg = parse_config(text.replace("vehicle_id: truck1", "vehicle_id: 2026-01-01", 1), "t.yaml")
    assert cfg.vehicle_id == "2026-01-01"
