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

The older frc-characterization tool (2019-2021) wrote the same four tests with rows of
ten numbers, ``[t, battery, autospeed, V_left, V_right, x_left, x_right, v_left, v_right,
gyro_angle]`` (:data:`FRC_CHARACTERIZATION`), positions and speeds in encoder rotations
times ``unitsPerRotation`` in its ``units`` (rotational units: one rotation); a file
without ``units`` (its first versions) keeps the file's own units, said in a note.  Its
arm, elevator and simple-motor tools wrote rows of six, ``[t, battery, autospeed, V, x,
v]``.  Its robot templates log the voltage unsigned: a backward test's is taken negative.
It is told from SysId's by its row width (no ``sysid`` key).

``FILE.json:slow-forward,slow-backward`` selects tests (default: all four).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace

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
    """``FILE.json:a,b`` -> ``("FILE.json", ("a", "b"))``; no selector -> all tests.

    A selector that names no test (``FILE.json:``) or one test twice is refused: each
    run is fitted once, and a typo is not read as the whole file."""
    head, sep, tail = path.rpartition(":")
    if not (sep and head.lower().endswith(".json")):
        return path, TESTS
    names = tuple(x.strip() for x in tail.split(",") if x.strip())
    if not names:
        raise InputError(
            f"{path}: no test named after ':'; expected {head}:TEST[,TEST...] with tests "
            f"from {', '.join(TESTS)}, or {head} alone for all of them"
        )
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InputError(f"{path}: test {twice[0]!r} named twice; each run is fitted once")
    return head, names


@dataclass(frozen=True)
class _Layout:
    """Where a file's rows keep voltage, position and speed, and how to read them."""

    kind: str
    """``drivetrain`` or ``simple`` (the messages' word for the test)."""
    width: int
    """Numbers per row."""
    u: tuple[int, ...]
    """Voltage column(s): left and right of a drivetrain, else one."""
    x: tuple[int, ...]
    v: tuple[int, ...]
    scale: float
    """File units to SI (m, or rad for rotational units)."""
    sign: float = 1.0
    """Weight of the left side (-1: a spin test, half the sides' difference)."""
    notes: list[str] = field(default_factory=list)
    legacy: bool = False
    """An frc-characterization file (its templates log the voltage unsigned)."""
    position_unit: str = "m"
    """``m``, or ``rad`` for a rotational unit system."""


FRC_CHARACTERIZATION: dict[str, tuple[int, ...]] = {"u": (3, 4), "x": (5, 6), "v": (7, 8)}
"""frc-characterization's row: t, battery, autospeed, then left and right motor volts,
encoder positions and speeds, and the gyro angle (its data_analyzer's column indices);
a mechanism other than a drivetrain uses the left side's."""
FRC_CHARACTERIZATION_WIDTH = 10
"""Numbers per frc-characterization row."""
FRC_MECHANISM: dict[str, tuple[int, ...]] = {"u": (3,), "x": (4,), "v": (5,)}
"""frc-characterization's arm, elevator and simple-motor tools (2020): rows of six,
``[t, battery, autospeed, V, x, v]``."""
FRC_MECHANISM_WIDTH = 6


def _first_row(raw: dict[str, object]) -> object:
    for name in TESTS:
        rows = raw.get(name)
        if isinstance(rows, list) and rows:
            return rows[0]
    return None


def _units(raw: dict[str, object], file: str) -> tuple[str, float]:
    """The file's unit system (lower case) and its factor to SI (:data:`UNITS`)."""
    unit_name = str(raw.get("units", "Meters")).lower()
    if unit_name not in UNITS:
        raise InputError(
            f"{file}: key 'units': {raw.get('units')!r}; expected one of SysId's unit "
            "systems: Meters, Feet, Inches, Centimeters, Millimeters, Radians, Rotations, "
            "Degrees"
        )
    return unit_name, UNITS[unit_name]


def _legacy_layout(raw: dict[str, object], file: str, test_kind: str, width: int) -> _Layout:
    """An frc-characterization file's layout: rows of ten (:data:`FRC_CHARACTERIZATION`)
    or, from its mechanism tools, of six (:data:`FRC_MECHANISM`)."""
    notes = [f"an frc-characterization file (rows of {width} numbers): read as such"]
    mechanism = width < FRC_CHARACTERIZATION_WIDTH
    drivetrain = not mechanism and ("drivetrain" in test_kind or "test" not in raw)
    if "units" in raw:
        unit_name, scale = _units(raw, file)
        if unit_name in ROTATIONAL:
            scale = UNITS["rotations"]  # encoder rotations, in rad
        else:  # encoder rotations times unitsPerRotation, in its units
            per_rot = raw.get("unitsPerRotation", 1.0)
            if not isinstance(per_rot, int | float) or isinstance(per_rot, bool):
                raise InputError(f"{file}: key 'unitsPerRotation': expected a number")
            if not (math.isfinite(per_rot) and per_rot > 0.0):
                raise InputError(f"{file}: key 'unitsPerRotation': {per_rot!r}, expected > 0")
            scale *= float(per_rot)
    else:
        scale = 1.0
        notes.append(
            "an frc-characterization file without units: positions and speeds are taken "
            "in the file's own units (m and m/s if it logged metres); the fits do not "
            "depend on them, the constants and the notes' sizes do"
        )
    table = FRC_MECHANISM if mechanism else FRC_CHARACTERIZATION
    cols = {c: table[c][: 2 if drivetrain else 1] for c in "uxv"}
    kind = "drivetrain" if drivetrain else "simple"
    return _Layout(kind, width, cols["u"], cols["x"], cols["v"], scale, 1.0, notes, True)


def _layout(raw: dict[str, object], file: str) -> _Layout:
    """The layout of a SysId file, or of an frc-characterization one (rows of 10)."""
    test_kind = str(raw.get("test", "")).lower()
    gravity = [GRAVITY[k] for k in GRAVITY if k in test_kind][:1]
    first = _first_row(raw)
    width = len(first) if isinstance(first, list) else 0
    if "sysid" not in raw and width >= FRC_CHARACTERIZATION_WIDTH:
        out = _legacy_layout(raw, file, test_kind, FRC_CHARACTERIZATION_WIDTH)
    elif "sysid" not in raw and width == FRC_MECHANISM_WIDTH:
        out = _legacy_layout(raw, file, test_kind, FRC_MECHANISM_WIDTH)
    else:
        scale = _units(raw, file)[1]
        drivetrain = "drivetrain" in test_kind
        sign = -1.0 if drivetrain and "angular" in test_kind else 1.0  # left side's weight
        if drivetrain:
            out = _Layout("drivetrain", 9, (1, 2), (3, 4), (5, 6), scale, sign)
        else:
            out = _Layout("simple", 4, (1,), (2,), (3,), scale)
    out.notes.extend(gravity)
    unit_name = str(raw.get("units", "")).lower()
    if unit_name in ROTATIONAL:
        out = replace(out, position_unit="rad")
        out.notes.append(
            f"units {raw.get('units')}: converted to rad, the speed in rad/s stands where a "
            "truck's m/s would: kV and kA are per radian (V s/rad, V s^2/rad), and the "
            "notes speak of the shaft's angle (rad), its speed (rad/s) and the torques on "
            "it (N m) where a truck's would speak of metres, m/s and newtons"
        )
    return out


def _column(a: np.ndarray, cols: tuple[int, ...], sign: float) -> np.ndarray:
    """One signal from its column(s): a drivetrain's right side plus ``sign`` times its
    left, over two; else the one column."""
    if len(cols) == 2:
        return np.asarray(0.5 * (a[:, cols[1]] + sign * a[:, cols[0]]), float)
    return np.asarray(a[:, cols[0]], float).copy()


def read_sysid(path: str) -> list[Log]:
    """The selected tests of a SysId (or frc-characterization) JSON file, one
    voltage-input log each (t, u, v, x)."""
    file, wanted = split_selector(path)
    text = read_text(file, "SysId JSON log", MAX_LOG_BYTES)  # a regular UTF-8 file, bounded
    try:
        raw = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{file}: not a SysId JSON file: {str(exc)[:80]}") from None
    if not isinstance(raw, dict):
        raise InputError(f"{file}: not a SysId JSON file: expected an object with tests")
    lay = _layout(raw, file)
    width, kind = lay.width, lay.kind
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
        u = _column(a, lay.u, lay.sign)
        x = _column(a, lay.x, lay.sign) * lay.scale
        v = _column(a, lay.v, lay.sign) * lay.scale
        notes = list(lay.notes)
        if lay.legacy and name.endswith("backward") and np.all(u >= 0.0) and np.median(v) < 0:
            # frc-characterization's templates log |V| (battery times |autospeed|); its
            # analyzer gives the voltage the speed's sign
            u = -u
            notes.append(
                f"{name}: the voltage is logged unsigned (as frc-characterization's robot "
                "templates log it): taken negative, the test's direction"
            )
        logs.append(
            Log(
                {"t": a[:, 0].copy(), "u": u, "v": v, "x": x},
                f"{file}:{name}",
                notes=notes,
                position_unit=lay.position_unit,
            )
        )
    if not logs:
        raise InputError(f"{file}: no SysId test found (expected keys {', '.join(TESTS)})")
    return logs
