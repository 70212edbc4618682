"""Real data: the EMPS rig (force input), against the published reference model.

The data ships in ``tests/data/emps`` (README there: provenance, licence): a missing file
fails the test, it does not skip it.  Published (Janot et al. 2019, IDIM-LS):
M = 95.1089 kg, Fv = 203.5034 N s/m, Fc = 20.3935 N, offset = -3.1648 N, force relative
error 4.0834 % on DATA_EMPS (training) and 5.9824 % on DATA_EMPS_PULSES (cross-test).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from truckd.cli.main import main
from truckd.ident.api import diagnose_log
from truckd.ident.emps import TEST, TRAIN, emps_dir, emps_log
from truckd.logfile import write_log
from truckd.model.params import VehicleParams


def test_emps_data_is_present(monkeypatch: pytest.MonkeyPatch) -> None:
    """The loader's default is the copy in this repository's tests/data/emps."""
    monkeypatch.delenv("TRUCKD_EMPS_DIR", raising=False)
    d = emps_dir()
    assert d == Path(__file__).resolve().parent / "data" / "emps"
    assert (d / TRAIN).is_file(), f"EMPS data missing in {d}"
    assert (d / TEST).is_file(), f"EMPS data missing in {d}"


def test_diagnose_finds_viscous_friction_and_offset(params: VehicleParams) -> None:
    train, test = emps_log(TRAIN), emps_log(TEST)
    d = diagnose_log(train, params, validate=test)
    assert d.input == "force"
    assert [f.name for f in d.effects] == ["viscous_friction", "load_force"]
    ext = d.extended.params
    assert ext["M"] == pytest.approx(95.1089, rel=0.01)
    assert ext["F_v"] == pytest.approx(203.5034, rel=0.02)
    assert ext["F_c"] == pytest.approx(20.3935, rel=0.02)
    assert ext["offset"] == pytest.approx(-3.1648, abs=0.1)
    # Cross-test force error, as published (5.9824 %), and far below the seed's.
    assert d.extended.force_relerr_percent == pytest.approx(5.98, abs=0.1)
    assert d.baseline.force_relerr_percent is not None
    assert d.baseline.force_relerr_percent > 2.0 * d.extended.force_relerr_percent
    assert d.extended.fit_percent > d.baseline.fit_percent + 50.0
    assert not any(a == "aero_drag" or b == "aero_drag" for a, b in d.ambiguous)


def test_training_error_matches_the_published_table(params: VehicleParams) -> None:
    train = emps_log(TRAIN)
    d = diagnose_log(train, params, validate=train)
    assert d.extended.force_relerr_percent == pytest.approx(4.0834, abs=0.1)


def test_cli_on_emps_csv(tmp_path: Path) -> None:
    """The contract CSV (t, F, x) through the command line, JSON per the contract."""
    write_log(tmp_path / "train.csv", emps_log(TRAIN).columns)
    write_log(tmp_path / "test.csv", emps_log(TEST).columns)
    out = tmp_path / "d.json"
    code = main(
        [
            "diagnose",
            str(tmp_path / "train.csv"),
            "--validate",
            str(tmp_path / "test.csv"),
            "--json",
            str(out),
        ]
    )
    assert code == 0
    j = json.loads(out.read_text())
    assert j["input"] == "force"
    assert [e["name"] for e in j["effects"]] == ["viscous_friction", "load_force"]
    assert j["extended"]["force_relerr_percent"] == pytest.approx(5.98, abs=0.1)
    assert "force_relerr_percent" in j["baseline"]
    # SysId's equation with the force as input, F = kS sign(v) + kV v + kA a, by OLS:
    # the published IDIM-LS values without the offset, and below the extended model
    assert j["linear_estimate"] is None  # a voltage drive's estimate: none, but the key is there
    ls = j["least_squares"]
    assert ls["kA"] == pytest.approx(95.11, rel=0.01) and ls["kS"] == pytest.approx(20.4, rel=0.03)
    assert ls["kV"] == pytest.approx(203.5, rel=0.02) and 0.0 < ls["kA_se"] < 0.01 * ls["kA"]
    assert ls["fit_percent"] < j["extended"]["fit_percent"]
    assert j["extended"]["fit_percent"] < j["fit_ceiling_percent"] < 100.0  # room is left
    # --out needs a truck (voltage) model: a clear error, exit 2.
    code = main(["diagnose", str(tmp_path / "train.csv"), "--out", str(tmp_path / "m.yaml")])
    assert code == 2
