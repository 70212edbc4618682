"""The shipped configuration and the specs agree: every default is written twice (the
dataclass specs, which a section takes when a key is absent, and ``config/truck.yaml``,
which documents them for the user), and this test fails on any difference, naming the key
and both values.  (Change a default: change it in both; the message says where.)"""

from __future__ import annotations

import dataclasses
from typing import Any, get_args, get_type_hints

import yaml

from truckd.config.truck import TruckConfig, default_config_path
from truckd.schema import to_plain

ABSENT = object()


def spec_defaults(cls: type, prefix: str = "") -> dict[str, Any]:
    """Dotted key -> default of every field of ``cls`` with one (nested sections walked)."""
    out: dict[str, Any] = {}
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        key = f"{prefix}{f.name}"
        tp = hints[f.name]
        section = next(
            (t for t in (tp, *get_args(tp)) if dataclasses.is_dataclass(t) and isinstance(t, type)),
            None,
        )
        if section is not None:
            out |= spec_defaults(section, key + ".")
        elif f.default is not dataclasses.MISSING:
            out[key] = to_plain(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            out[key] = to_plain(f.default_factory())
    return out


def yaml_leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(node, dict):
        out: dict[str, Any] = {}
        for k, v in node.items():
            out |= yaml_leaves(v, f"{prefix}{k}.")
        return out
    return {prefix[:-1]: node}


def differences(shipped: dict[str, Any], specs: dict[str, Any]) -> list[str]:
    found = []
    for key, default in specs.items():
        value = shipped.get(key, ABSENT)
        if key.startswith("vehicle."):
            continue  # required: the shipped truck's own values, no default
        if value is ABSENT and default is None:
            continue  # optional key, absent means "none" (plant.vehicle.*)
        if value is ABSENT:
            found.append(f"{key}: missing from truck.yaml (spec default {default!r})")
        elif value != default or type(value) is not type(default):
            found.append(f"{key}: truck.yaml {value!r}, spec default {default!r}")
    return found


def test_the_shipped_yaml_holds_every_spec_default() -> None:
    shipped = yaml_leaves(yaml.safe_load(default_config_path().read_text(encoding="utf-8")))
    specs = spec_defaults(TruckConfig)
    assert len(specs) > 150  # the walk sees every section
    assert differences(shipped, specs) == []


def test_a_difference_is_found() -> None:
    """The check can fail: a changed value, a dropped key, an int for a float."""
    specs = spec_defaults(TruckConfig)
    shipped = yaml_leaves(yaml.safe_load(default_config_path().read_text(encoding="utf-8")))
    changed = {**shipped, "control.horizon": 41, "link.timeout_periods": 5}
    del changed["runtime.recorder.keep"]
    assert sorted(differences(changed, specs)) == [
        "control.horizon: truck.yaml 41, spec default 40",
        "link.timeout_periods: truck.yaml 5, spec default 5.0",
        "runtime.recorder.keep: missing from truck.yaml (spec default 20)",
    ]


def test_encoder_ticks_per_revolution_is_written_once() -> None:
    """``link.encoder_ticks_per_rev``'s default is the one literal in the package: the
    controller takes the configured value (``TruckConfig.ticks_per_rev``, the plant's
    encoder when it models one), the simulator's defaults take the spec's."""
    import re
    from pathlib import Path

    from truckd.io.config import ENCODER_TICKS_PER_REV

    root = Path(__file__).resolve().parents[1] / "truckd"
    literal = re.compile(rf"\b{ENCODER_TICKS_PER_REV}\b")
    found = sorted(
        str(p.relative_to(root))
        for p in root.rglob("*.py")
        if literal.search(p.read_text(encoding="utf-8"))
    )
    assert found == ["io/config.py"]
    shipped = yaml.safe_load(default_config_path().read_text(encoding="utf-8"))
    assert shipped["link"]["encoder_ticks_per_rev"] == ENCODER_TICKS_PER_REV


def test_the_repository_config_is_the_packaged_file() -> None:
    """``config/truck.yaml`` (what the README points a user to) is a link to the file the
    package ships and loads by default, not a second copy that could drift."""
    repo = default_config_path().parents[2] / "config" / "truck.yaml"
    assert repo.is_symlink()
    assert repo.resolve() == default_config_path().resolve()
