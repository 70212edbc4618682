"""Honest words: the noise level survives sample-and-hold speed, "white" needs the
cross-correlation with the input too, and SysId logs come in any of its unit systems."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from truckd.errors import InputError
from truckd.ident.data import noise_std
from truckd.ident.residuals import Whiteness
from truckd.ident.selection import structured, white
from truckd.ident.sysid import read_sysid


@pytest.mark.parametrize("hold", [1, 2, 4, 10])
def test_noise_level_of_a_sampled_and_held_speed(hold: int) -> None:
    """A speed that updates every ``hold``-th sample repeats its value in between: the
    second difference is mostly 0, and its MAD gave a noise level of 0."""
    rng = np.random.default_rng(hold)
    t = np.arange(8000) * 0.005
    sd = 0.02
    fresh = np.sin(0.5 * t) + sd * rng.standard_normal(len(t))
    held = np.repeat(fresh[::hold], hold)[: len(t)]
    assert noise_std(held) == pytest.approx(sd, rel=0.15)


def test_white_needs_the_cross_correlation_with_the_input() -> None:
    """A residual whose autocorrelation is in the band but that follows the input (59 %
    of the cross-correlation lags outside the band) is not white, and is structured when
    it exceeds the noise."""
    wt = Whiteness(rms=0.05, noise=0.01, structure=0.049, acf_outside=0.05, ccf_outside=0.59)
    assert not white(wt)
    assert structured(wt, 0.01, 0.0)
    clean = Whiteness(rms=0.0101, noise=0.01, structure=0.001, acf_outside=0.05, ccf_outside=0.05)
    assert white(clean)
    assert not structured(clean, 0.01, 0.0)


UNIT = {
    "Meters": 1.0,
    "Feet": 0.3048,
    "Inches": 0.0254,
    "Radians": 1.0,
    "Rotations": 2.0 * np.pi,
    "Degrees": np.pi / 180.0,
}


@pytest.mark.parametrize("units", sorted(UNIT))
def test_sysid_logs_in_every_unit_system(tmp_path: Path, units: str) -> None:
    rows = [[0.01 * k, 1.0 + 0.01 * k, 0.02 * k, 0.5 + 0.001 * k] for k in range(50)]
    path = tmp_path / "sysid.json"
    path.write_text(
        json.dumps({"test": "Simple", "units": units, "slow-forward": rows}), encoding="utf-8"
    )
    (log,) = read_sysid(str(path))
    v = np.asarray(log.columns["v"])
    assert v[10] == pytest.approx((0.5 + 0.01) * UNIT[units])
    # a rotational unit is carried with the log, and said
    rotational = units in ("Radians", "Rotations", "Degrees")
    assert log.position_unit == ("rad" if rotational else "m")
    assert any("per radian" in n for n in log.notes) == rotational


@pytest.mark.parametrize("test", ["Drivetrain", "Drivetrain (Angular)"])
def test_a_drivetrain_is_its_straight_line_or_its_spin(tmp_path: Path, test: str) -> None:
    """A drivetrain's sides: their mean on the straight-line test; on the spin test, where
    the left side is driven backwards, half the difference (right minus left): the mean
    of a spin is noise about 0 V and 0 m/s."""
    rows = []
    for k in range(50):
        u, x, v = 2.0 + 0.01 * k, 0.02 * k, 0.4 + 0.001 * k
        side = -1.0 if "Angular" in test else 1.0  # the left side's sign
        rows.append([0.01 * k, side * 0.98 * u, 1.02 * u, side * x, x, side * 0.99 * v, 1.01 * v,
                     0.0, 0.0])  # fmt: skip
    path = tmp_path / "dt.json"
    path.write_text(json.dumps({"test": test, "units": "Meters", "fast-forward": rows}))
    (log,) = read_sysid(str(path))
    assert log.columns["u"][10] == pytest.approx(2.1)
    assert log.columns["v"][10] == pytest.approx(0.41)
    assert log.columns["x"][10] == pytest.approx(0.2)


@pytest.mark.parametrize(
    ("head", "scale", "simple"),
    [
        ({}, 1.0, False),  # its first versions: drivetrains, no units
        ({"test": "Drivetrain", "units": "Feet", "unitsPerRotation": 0.5}, 0.5 * 0.3048, False),
        ({"test": "Simple", "units": "Rotations", "unitsPerRotation": 1.0}, 2.0 * np.pi, True),
    ],
)
def test_an_frc_characterization_file_is_read_as_such(
    tmp_path: Path, head: dict[str, object], scale: float, simple: bool
) -> None:
    """The older tool's rows of ten, [t, battery, autospeed, V_l, V_r, x_l, x_r, v_l, v_r,
    gyro], in encoder rotations times unitsPerRotation: read as SysId's four-number rows,
    the battery was the voltage and the motor's volts the speed (fits of -200 %)."""
    rows = []
    for k in range(50):
        u, x, v = 2.0 + 0.01 * k, 0.02 * k, 0.4 + 0.001 * k
        rows.append([0.02 * k, 12.3, 0.2, 0.98 * u, 1.02 * u, 0.99 * x, 1.01 * x,
                     0.99 * v, 1.01 * v, 5.0])  # fmt: skip
    path = tmp_path / "characterization.json"
    path.write_text(json.dumps({**head, "slow-forward": rows}), encoding="utf-8")
    (log,) = read_sysid(str(path))
    side = 0.99 if simple else 1.0  # a mechanism other than a drivetrain: the left side
    assert log.columns["u"][10] == pytest.approx((0.98 if simple else 1.0) * 2.1)
    assert log.columns["v"][10] == pytest.approx(side * 0.41 * scale)
    assert log.columns["x"][10] == pytest.approx(side * 0.2 * scale)
    assert any("frc-characterization" in n for n in log.notes)
    assert any("without units" in n for n in log.notes) == ("units" not in head)
    assert log.position_unit == ("rad" if head.get("units") == "Rotations" else "m")


def test_an_unknown_unit_system_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "sysid.json"
    rows = [[0.01 * k, 1.0, 0.0, 0.5] for k in range(5)]
    path.write_text(json.dumps({"units": "Furlongs", "slow-forward": rows}), encoding="utf-8")
    with pytest.raises(InputError, match="Rotations"):
        read_sysid(str(path))


@pytest.mark.parametrize("hold", [4, 10])
def test_a_sampled_and_held_speed_is_explained_by_the_clean_model(hold: int) -> None:
    """A clean truck whose speed sensor updates every ``hold``-th sample: compared at its
    fresh readings, the model explains it (nothing named, not unexplained) and beats the
    least squares, which the staircase biases (a held value is a stale one)."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    log = plant_log(p, Effects(), seed=9, n=3000, with_current=False)
    cols = dict(log.columns)
    v = np.asarray(cols["v"])
    cols["v"] = np.repeat(v[::hold], hold)[: len(v)]
    d = diagnose_log(Log(cols, f"<held every {hold}>"), p)
    assert [f.name for f in d.effects] == []
    assert not d.unexplained
    ls = d.least_squares
    assert ls is not None and ls["fit_percent"] is not None
    assert d.extended.fit_percent >= ls["fit_percent"]


def test_isolated_speed_spikes_are_replaced_and_said() -> None:
    """A clean truck's log with a few wild speed samples (a sensor's glitch: 50 times the
    top speed for one sample): the spikes are replaced by their neighbours' mean and said
    in the alerts, and the diagnosis is the clean log's (nothing named, the fit within
    0.2 points of it); a white residual far above the noise would not explain the data."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.ident.data import despiked
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    log = plant_log(p, Effects(), seed=5, n=3000, with_current=False)
    cols = dict(log.columns)
    v = np.array(cols["v"], dtype=float)
    wild = [400, 1300, 2200]
    v[wild] = [50.0 * np.max(np.abs(v)), -30.0 * np.max(np.abs(v)), 9.0]
    cols["v"] = v
    clean = diagnose_log(log, p)
    d = diagnose_log(Log(cols, "<spiked>"), p)
    assert [f.name for f in d.effects] == [f.name for f in clean.effects] == []
    assert abs(d.extended.fit_percent - clean.extended.fit_percent) < 0.2
    assert any("3 isolated spike(s)" in a for a in d.alerts), d.alerts
    # the speed's own steps and a held (staircase) speed are not spikes
    from truckd.ident.data import Series

    t = np.arange(200) * 0.01
    steps = Series(t=t, inp=np.ones(200), v=np.repeat(np.arange(50.0), 4), i=None, x=None)
    assert despiked(steps)[1] == 0


def test_a_white_residual_far_above_the_noise_does_not_explain_the_data() -> None:
    """White (no lag outside the band) but 100 times the noise: not at the noise level."""
    from truckd.ident.selection import at_noise_level

    loud = Whiteness(rms=1.0, noise=0.01, structure=1.0, acf_outside=0.0, ccf_outside=0.0)
    assert white(loud) and not at_noise_level(loud, 0.01, 0.0)
    quiet = Whiteness(rms=0.012, noise=0.01, structure=0.007, acf_outside=0.0, ccf_outside=0.0)
    assert at_noise_level(quiet, 0.01, 0.0)


def _first_order_sysid(path: Path, units: str = "Meters") -> None:
    """A noise-free first-order drivetrain in SysId's JSON (both sides alike): ramps at
    0.25 V/s and 6 V steps each way, breakaway 0.3 V, 0.5 m/s per volt above it (per
    ``units``), time constant 0.3 s, Euler-integrated at 5 ms."""
    doc: dict[str, object] = {"sysid": True, "test": "Drivetrain", "units": units}
    for name, sign, ramp in [
        ("slow-forward", 1.0, True),
        ("slow-backward", -1.0, True),
        ("fast-forward", 1.0, False),
        ("fast-backward", -1.0, False),
    ]:
        n, dt = (1000 if ramp else 300), 0.005
        t = np.arange(n) * dt + (0.0 if ramp else 50.0) + (100.0 if sign < 0 else 0.0)
        u = sign * 0.25 * np.arange(n) * dt if ramp else np.full(n, sign * 6.0)
        drive = np.where(np.abs(u) > 0.3, u - sign * 0.3, 0.0)
        v, x = np.zeros(n), np.zeros(n)
        for j in range(1, n):
            v[j] = v[j - 1] + dt * (0.5 * drive[j - 1] - v[j - 1]) / 0.3
            x[j] = x[j - 1] + dt * v[j - 1]
        doc[name] = np.c_[t, u, u, x, x, v, v, np.zeros(n), np.zeros(n)].tolist()
    path.write_text(json.dumps(doc), encoding="utf-8")


def test_a_cause_that_moves_nothing_is_not_named(tmp_path: Path) -> None:
    """On a noise-free log that the seed model fits to a few 1e-4 m/s, a cause whose
    fitted size is nothing (a backlash of 1e-12 rad, a resistance drift of 1e-6) must not
    be named on the strength of what the joint refit moved in the seed's parameters."""
    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log

    path = tmp_path / "first_order.json"
    _first_order_sysid(path)
    d = diagnose_log(read_sysid(str(path)), load_config().vehicle)
    assert [(f.name, f.params) for f in d.effects] == []
    assert d.extended.fit_percent > 99.9


@pytest.mark.parametrize(("units", "per"), [("Meters", "m"), ("Radians", "rad")])
def test_the_constants_are_printed_in_the_logs_units(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], units: str, per: str
) -> None:
    """A flywheel's SysId file in rad: kV and kA per radian in the text and the report,
    and the JSON says which (they were printed per metre whatever the file's units)."""
    from truckd.cli.main import main

    path, out = tmp_path / "first_order.json", tmp_path / "d.json"
    _first_order_sysid(path, units)
    assert main(["diagnose", f"{path}:slow-forward,fast-forward", "--json", str(out),
                 "--jobs", "1", "--report", str(tmp_path / "rep")]) == 0  # fmt: skip
    text = capsys.readouterr().out
    for line in ("least squares:", "feedforward (SysId form):"):
        (said,) = [ln for ln in text.splitlines() if ln.startswith(line)]
        assert f" V s/{per}," in said and f" V s^2/{per}" in said
    assert json.loads(out.read_text())["position_unit"] == per
    page = (tmp_path / "rep" / "index.html").read_text()
    assert f"V s/{per}," in page


def test_a_rotating_and_a_translating_log_are_not_fitted_together(tmp_path: Path) -> None:
    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log

    rad, metre = tmp_path / "rad.json", tmp_path / "m.json"
    _first_order_sysid(rad, "Rotations")
    _first_order_sysid(metre)
    with pytest.raises(InputError, match=r"positions are in m, those of .* in rad"):
        diagnose_log(read_sysid(f"{rad}:slow-forward"), load_config().vehicle,
                     read_sysid(f"{metre}:fast-forward"))  # fmt: skip


def test_a_speed_of_the_wrong_sign_and_a_time_in_milliseconds_are_said() -> None:
    """Columns that look wired or scaled wrongly are named with their numbers."""
    from truckd.ident.data import Series
    from truckd.ident.verdict import suspect_columns

    t = np.arange(400) * 0.01
    u = np.where(np.arange(400) % 200 < 100, 3.0, -3.0)
    v = np.convolve(u, np.full(20, 0.05 / 3.0), "same")
    good = Series(t=t, inp=u, v=v, i=None, x=None)
    assert suspect_columns([good]) == []
    (sign,) = suspect_columns([Series(t=t, inp=u, v=-v, i=None, x=None)])
    assert "the speed falls as the voltage rises" in sign
    (slow,) = suspect_columns([Series(t=1000.0 * t, inp=u, v=v, i=None, x=None)])
    assert "median time step is 10 s" in slow


def test_sysid_rows_are_numbers_and_gravity_is_said(tmp_path: Path) -> None:
    """A row of booleans or a short row is refused naming the row; an Elevator or Arm
    test carries a note on what its gravity does to the fit."""
    rows = [[0.01 * k, 1.0, 0.02 * k, 0.5] for k in range(20)]
    path = tmp_path / "s.json"
    bad = [*rows[:5], [0.05, True, True, True], *rows[6:]]
    path.write_text(json.dumps({"test": "Simple", "slow-forward": bad}), encoding="utf-8")
    with pytest.raises(InputError, match="key 'slow-forward': row 5: expected 4 numbers"):
        read_sysid(str(path))
    path.write_text(json.dumps({"test": "Simple", "slow-forward": [*rows[:3], [0.1]]}))
    with pytest.raises(InputError, match="row 3"):
        read_sysid(str(path))
    path.write_text(
        json.dumps({"test": "Simple", "slow-forward": [*rows[:2], [0.1, 10**400, 0, 0]]})
    )
    with pytest.raises(InputError, match="row 2"):  # a number no float holds
        read_sysid(str(path))
    path.write_text(json.dumps({"test": "Elevator", "slow-forward": rows}), encoding="utf-8")
    (log,) = read_sysid(str(path))
    assert any("gravity" in n for n in log.notes)


def test_a_current_column_left_out_is_said() -> None:
    """Two runs, one with current and one without: fitted together on speed alone, and
    the alerts say that the current column was not used."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    with_i = plant_log(p, Effects(), seed=3, n=1500, with_current=True)
    without = plant_log(p, Effects(), seed=4, n=1500, with_current=False)
    d = diagnose_log([Log(with_i.columns, "<with i>"), Log(without.columns, "<no i>")], p)
    assert any("current column of <with i> is not used" in a for a in d.alerts), d.alerts


@pytest.mark.parametrize(("sd", "hold"), [(0.005, 1), (0.05, 1), (0.02, 4)])
def test_the_noise_ceiling_is_the_fit_of_the_true_speed(sd: float, hold: int) -> None:
    """The ceiling (``fit_ceiling_percent``) is what the noise-free speed itself fits the
    measured one: the same drawn truck simulated with and without speed noise, its speed
    sampled and held every ``hold``-th sample (compared at the fresh readings)."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.data import fit_ceiling_percent, fresh_mask, series_from_log
    from truckd.ident.voltage import fit_percent
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    clean = plant_log(p, Effects(), seed=21, n=4000, noise_v=0.0, with_current=False)
    noisy = plant_log(p, Effects(), seed=21, n=4000, noise_v=sd, with_current=False)
    v = np.asarray(noisy["v"])
    held = np.repeat(v[::hold], hold)[: len(v)]
    fresh = fresh_mask(held)
    truth = fit_percent(held[fresh], np.asarray(clean["v"])[fresh])
    log = Log({**noisy.columns, "v": held}, "<noisy>")
    ceiling = fit_ceiling_percent([series_from_log(log)])
    assert ceiling is not None and truth < 99.9
    assert ceiling == pytest.approx(truth, abs=0.3 + 0.05 * (100.0 - truth))


@pytest.mark.parametrize(
    ("steps", "sd"), [(40, 0.0), (200, 0.0), (40, 0.01), (40, 0.1), (200, 0.02)]
)
def test_the_noise_ceiling_counts_a_grids_rounding(steps: int, sd: float) -> None:
    """A speed read on a grid (``steps`` encoder counts over its range, with white noise
    ``sd`` m/s before the rounding): the ceiling is what the true speed fits the rounded
    one, not 100 % (its second difference is mostly zero)."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.data import fit_ceiling_percent, series_from_log
    from truckd.ident.voltage import fit_percent
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    clean = np.asarray(plant_log(p, Effects(), seed=22, n=4000, noise_v=0.0)["v"])
    noisy = plant_log(p, Effects(), seed=22, n=4000, noise_v=sd)
    q = float(np.ptp(clean)) / steps
    read = q * np.round(np.asarray(noisy["v"]) / q)
    truth = fit_percent(read, clean)
    ceiling = fit_ceiling_percent([series_from_log(Log({**noisy.columns, "v": read}, "<grid>"))])
    assert ceiling is not None and truth < 99.9
    assert ceiling == pytest.approx(truth, abs=0.3 + 0.05 * (100.0 - truth))


@pytest.mark.parametrize("inertia", [0.3, 0.1])
def test_the_noise_ceiling_is_never_below_the_best_fit(inertia: float) -> None:
    """A light truck (``inertia`` times the default's) driven by levels held 0.1 s: its
    speed moves within a sample, and the second difference counts that motion as noise
    (the noise alone would put the ceiling below the fits).  The diagnosis' ceiling is at
    least its best model's fit: a model that fits better shows the noise is smaller."""
    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.ident.data import fit_ceiling_percent, series_from_log
    from truckd.logfile import Log
    from truckd.model.effects import Effects
    from truckd.model.plant_config import PlantConfig
    from truckd.sim.plant import simulate_open_loop

    p0 = load_config().vehicle
    p = dataclasses.replace(p0, J_S=p0.J_S * inertia, m=p0.m * inertia)
    rng = np.random.default_rng(5)
    t = np.arange(3000) * 0.01
    u = np.repeat(rng.uniform(-6.0, 6.0, 300), 10)
    cfg = PlantConfig(effects=Effects(), noise_v=0.005, noise_i=0.1, seed=5)
    log = Log({"t": t, "u": u, "v": simulate_open_loop(p, t, u, cfg).v}, "<light truck>")
    d = diagnose_log(log, p0)
    noise_only = fit_ceiling_percent([series_from_log(log)])
    assert noise_only is not None and noise_only < d.extended.fit_percent  # the case arises
    assert d.fit_ceiling is not None and d.fit_ceiling >= d.extended.fit_percent


def test_the_readers_notes_are_in_the_diagnosis_once() -> None:
    """What a reader says of its logs (a SysId file's units, the input column) is in the
    diagnosis' notes, once however many of its tests are given: the JSON lacked it."""
    from labkit.synth import plant_log

    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.logfile import Log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    said = "units Rotations: converted to rad"
    logs = [
        Log(plant_log(p, Effects(), seed=s, n=1500, with_current=False).columns, f"<{s}>",
            notes=[said])
        for s in (4, 5)
    ]  # fmt: skip
    d = diagnose_log(logs, p)
    assert d.notes.count(said) == 1
    assert d.to_json()["notes"].count(said) == 1


def test_frc_characterization_mechanisms_and_unsigned_voltages(tmp_path: Path) -> None:
    """Its arm, elevator and simple-motor tools wrote rows of six, [t, battery,
    autospeed, V, x, v] (read as SysId's four, the battery was the voltage); its robot
    templates log |V| (battery times |autospeed|), so a backward test's voltage is
    positive while the truck reverses: taken negative, and said."""
    fwd, back = [], []
    for k in range(50):
        u, x, v = 2.0 + 0.01 * k, 0.02 * k, 0.4 + 0.001 * k
        fwd.append([0.02 * k, 12.3, 0.2, u, x, v])
        back.append([0.02 * k, 12.3, -0.2, u, -x, -v])  # |V| logged
    path = tmp_path / "arm.json"
    raw = {"test": "Arm", "units": "Rotations", "slow-forward": fwd, "slow-backward": back}
    path.write_text(json.dumps(raw), encoding="utf-8")
    f, b = read_sysid(str(path))
    assert f.columns["u"][10] == pytest.approx(2.1)
    assert f.columns["v"][10] == pytest.approx(0.41 * 2.0 * np.pi)
    assert b.columns["u"][10] == pytest.approx(-2.1)
    assert b.columns["v"][10] == pytest.approx(-0.41 * 2.0 * np.pi)
    assert any("unsigned" in n for n in b.notes) and not any("unsigned" in n for n in f.notes)
    assert any("gravity" in n for n in f.notes)  # an Arm: what its gravity does


@pytest.mark.parametrize(
    ("column", "scale", "said"),
    # the current 50x (this log's 103 A peaks in mA exceed the reader's 10 000 A bound)
    [(None, 1.0, None), ("i", 50.0, "(not mA)?"), ("v", 225.0, "(not rpm or rad/s)?"),
     ("t", 1000.0, "is t in seconds?")],
)  # fmt: skip
def test_identify_and_diagnose_say_a_column_in_the_wrong_unit(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    column: str | None,
    scale: float,
    said: str | None,
) -> None:
    """A current in mA, a speed in rpm, a time in ms: both commands say it (identify
    said nothing and wrote the model: R_m 0.00033 ohm from a current in mA)."""
    from labkit.synth import plant_log

    from truckd.cli.main import main
    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.logfile import Log, write_log
    from truckd.model.effects import Effects

    p = load_config().vehicle
    cols = dict(plant_log(p, Effects(), seed=7, n=1500).columns)
    if column is not None:
        cols[column] = cols[column] * scale
    path = tmp_path / "log.csv"
    write_log(path, cols)
    assert main(["identify", str(path), "--out", str(tmp_path / "m.yaml")]) == 0
    notes = capsys.readouterr().err
    units = ("(not mA)?", "(not rpm or rad/s)?", "is t in seconds?")
    assert [u for u in units if u in notes] == ([] if said is None else [said])
    d = diagnose_log([Log(cols, str(path))], p, workers=1)
    assert [u for u in units if any(u in a for a in d.alerts)] == ([] if said is None else [said])


def test_identify_refuses_a_rotating_and_a_translating_log_together(tmp_path: Path) -> None:
    from truckd.cli.main import main

    rad, metre = tmp_path / "rad.json", tmp_path / "m.json"
    _first_order_sysid(rad, "Radians")
    _first_order_sysid(metre)
    out = tmp_path / "m.yaml"
    assert main(["identify", str(rad), str(metre), "--out", str(out)]) == 2
    assert not out.exists()


def test_identify_prints_the_constants_per_radian(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from truckd.cli.main import main

    path = tmp_path / "rad.json"
    _first_order_sysid(path, "Rotations")
    assert main(["identify", str(path), "--out", str(tmp_path / "m.yaml")]) == 0
    (line,) = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("feedforward")]
    assert " V s/rad," in line and line.endswith(" V s^2/rad")


@pytest.mark.parametrize(
    ("truck", "rotating"),
    [
        ("drag at 67 m/s = 0.687 N exceeds the weight 0.471 N",
         "drag at 67 rad/s = 0.687 N m exceeds the weight 0.471 N m"),
        ("RMS 3.68 against noise 0.0928 m/s); it", "RMS 3.68 against noise 0.0928 rad/s); it"),
        ("residual periodic in position (488 m): rolling",
         "residual periodic in position (488 rad): rolling"),
        ("a peak of 2 m/s^2", "a peak of 2 rad/s^2"),
        ("K_coulomb = 0.1 N m at or above", "K_coulomb = 0.1 N m at or above"),
        ("(J_S = 1.6e-09 kg m^2): wheels", "(J_S = 1.6e-09 kg m^2): wheels"),
        ("kV=0.5 V s/m, 2 N s/m", "kV=0.5 V s/m, 2 N s/m"),
    ],
)  # fmt: skip
def test_a_rotating_machines_notes_speak_of_its_units(truck: str, rotating: str) -> None:
    from truckd.ident.rotational import in_rotational_units

    assert in_rotational_units(truck) == rotating


def test_the_same_log_in_rad_is_said_in_rad_s_and_newton_metres(tmp_path: Path) -> None:
    """The same numbers in a file in Meters and one in Radians, with a swing at 0.7 Hz
    no input explains (the diagnosis says it with its RMS and the noise, in m/s): the
    Radians file's notes are the Meters file's, each unit said as the shaft's."""
    from truckd.config.truck import load_config
    from truckd.ident.api import diagnose_log
    from truckd.ident.rotational import in_rotational_units

    notes = {}
    for units in ("Meters", "Radians"):
        path = tmp_path / f"{units}.json"
        _first_order_sysid(path, units)
        doc = json.loads(path.read_text())
        for rows in doc.values():
            if isinstance(rows, list):
                for row in rows:
                    swing = 0.1 * np.sin(2.0 * np.pi * 0.7 * row[0])
                    row[5] += swing
                    row[6] += swing
        path.write_text(json.dumps(doc), encoding="utf-8")
        d = diagnose_log(read_sysid(str(path)), load_config().vehicle)
        notes[units] = [n for n in d.notes if not n.startswith("units ")]
    with_speed = [n for n in notes["Meters"] if re.search(r"\d m/s\b", n)]
    assert with_speed, notes["Meters"]
    assert notes["Radians"] == [in_rotational_units(n) for n in notes["Meters"]]
    assert not [n for n in notes["Radians"] if re.search(r"\d (m|m/s|N)\b(?! m)", n)]
