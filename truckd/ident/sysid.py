"""WPILib SysId JSON logs as contract logs (one :class:`Log` per test).

A SysId data file holds up to four tests, ``slow-forward``, ``slow-backward`` (quasi-static
voltage ramps) and ``fast-forward``, ``fast-backward`` (voltage steps), each a list of rows.
Drivetrain rows are ``[t, V_left, V_right, x_left, x_right, v_left, v_right, angle,
angular_rate]``; the other mechanisms' rows are ``[t, V, x, v]``.  A drivetrain becomes
the mean of its left and right sides (the robot's straight-line voltage and speed); the
spin test (``Drivetrain (Angular)``: the sides driven against each other) half their
difference, right minus left (each side's voltage and wheel speed as the robot turns
counter-clockwise, SysId's angular model in linear units);
``units`` any of SysId's unit systems (:data:`UNITS`): linear ones converted to m,
rotational ones (``Radians``, ``Rotations``, ``Degrees``) to rad, whose speed in rad/s
then stands for the speed (the fitted constants are per radian; the configured gearing
is only a prior, see docs/diagnosis.md).  Each test is one experiment (run).

``FILE.json:slow-forward,slow-backward`` selects tests (default: all four).
"""

from __future__ import annotations

import json

import numpy as np

from truckd.errors import InputError
from truckd.inputs import read_text
from truckd.logfile import MAX_LOG_BYTES, Log

TESTS = ("slow-forward", "slow-backward", "fast-forward", "fast-backward")
UNITS = {
    "meters": 1.0,
    "feet": 0.3048,
    "inches": 0.0254,
    "centimeters": 0.01,
    "millimeters": 0.001,
    "radians": 1.0,
    "rotations": 2.0 * np.pi,
    "degrees": np.pi / 180.0,
}
"""SysId's unit systems and the factor to SI: linear ones to metres; rotational ones to
radians (a flywheel's or arm's speed in rad/s then stands where a truck's m/s would)."""
ROTATIONAL = ("radians", "rotations", "degrees")


GRAVITY = {
    "elevator": "a SysId Elevator test: gravity (SysId's kG) acts as a constant load against "
    "the climb, which the diagnosis may name load_force",
    "arm": "a SysId Arm test: gravity on the arm (SysId's kG cos(angle)) changes with the "
    "angle; the model has no such term, it shows as a load changing with position",
}
"""What a mechanism's gravity does to the fit (the model is a drive on level ground)."""


def _check_rows(rows: object, where: str, width: int, kind: str) -> None:
    """Every row a list of at least ``width`` numbers (not booleans, not text); ``kind``
    names the test (``drivetrain``, ``simple``) in the message."""
    if not isinstance(rows, list):
        raise InputError(f"{where}: expected a list of rows, got {type(rows).__name__}")
    for k, row in enumerate(rows):
        ok = isinstance(row, list) and len(row) >= width
        ok = ok and all(
            isinstance(x, int | float) and not isinstance(x, bool) and abs(x) < 1e300
            for x in row[:width]
        )
        if not ok:
            raise InputError(
                f"{where}: row {k}: expected {width} numbers ({kind} test), got {str(row)[:60]}"
            )


def is_sysid_path(path: str) -> bool:
    """A path (optionally with ``:test,...``) that names a SysId ``.json`` file."""
    return split_selector(path)[0].lower().endswith(".json")


def split_selector(path: str) -> tuple[str, tuple[str, ...]]:
    """``FILE.json:a,b`` -> ``("FILE.json", ("a", "b"))``; no selector -> all tests."""
    head, sep, tail = path.rpartition(":")
    if sep and head.lower().endswith(".json") and tail:
        return head, tuple(x.strip() for x in tail.split(",") if x.strip())
    return path, TESTS


def read_sysid(path: str) -> list[Log]:
    """The selected tests of a SysId JSON file, one voltage-input log each (t, u, v, x)."""
    file, wanted = split_selector(path)
    text = read_text(file, "SysId JSON log", MAX_LOG_BYTES)  # a regular UTF-8 file, bounded
    try:
        raw = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{file}: not a SysId JSON file: {str(exc)[:80]}") from None
    if not isinstance(raw, dict):
        raise InputError(f"{file}: not a SysId JSON file: expected an object with tests")
    unit_name = str(raw.get("units", "Meters")).lower()
    if unit_name not in UNITS:
        raise InputError(
            f"{file}: key 'units': {raw.get('units')!r}; expected one of SysId's unit "
            "systems: Meters, Feet, Inches, Centimeters, Millimeters, Radians, Rotations, "
            "Degrees"
        )
    scale = UNITS[unit_name]
    test_kind = str(raw.get("test", "")).lower()
    drivetrain = "drivetrain" in test_kind
    sign = -1.0 if drivetrain and "angular" in test_kind else 1.0  # left side's weight
    width = 9 if drivetrain else 4
    kind = "drivetrain" if drivetrain else "simple"
    notes = [GRAVITY[k] for k in GRAVITY if k in test_kind][:1]
    if unit_name in ROTATIONAL:
        notes.append(
            f"units {raw.get('units')}: converted to rad, the speed in rad/s stands where a "
            "truck's m/s would: kV and kA printed per metre (V s/m, V s^2/m) are per "
            "radian (V s/rad, V s^2/rad), and forces and weights in the notes are the "
            "torques over the configured wheel radius"
        )
    logs: list[Log] = []
    for name in wanted:
        if name not in TESTS:
            raise InputError(f"{path}: unknown test {name!r}; expected one of {', '.join(TESTS)}")
        rows = raw.get(name)
        if rows is None:
            if wanted is TESTS:
                continue
            raise InputError(f"{file}: key {name!r} missing")
        _check_rows(rows, f"{file}: key {name!r}", width, kind)
        a = np.asarray([row[:width] for row in rows], dtype=float).reshape(-1, width)
        if len(a) < 2:
            raise InputError(
                f"{file}: key {name!r}: expected rows of {width} numbers ({kind} test)"
            )
        if not np.all(np.isfinite(a[:, :width])):
            raise InputError(f"{file}: key {name!r}: a value is not finite")
        order = np.argsort(a[:, 0], kind="stable")
        a = a[order]
        keep = np.concatenate([[True], np.diff(a[:, 0]) > 0])
        a = a[keep]
        if drivetrain:
            u = 0.5 * (a[:, 2] + sign * a[:, 1])
            x = 0.5 * (a[:, 4] + sign * a[:, 3]) * scale
            v = 0.5 * (a[:, 6] + sign * a[:, 5]) * scale
        else:
            u, x, v = a[:, 1], a[:, 2] * scale, a[:, 3] * scale
        logs.append(
            Log({"t": a[:, 0].copy(), "u": u, "v": v, "x": x}, f"{file}:{name}", notes=notes)
        )
    if not logs:
        raise InputError(f"{file}: no SysId test found (expected keys {', '.join(TESTS)})")
    return logs
