"""``truckd diagnose`` / ``truckd identify`` from the command line: files, JSON, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from labkit.synth import plant_log, with_effect

from truckd.cli.main import main
from truckd.logfile import write_log
from truckd.model.params import VehicleParams
from truckd.modelfile import read_model

CONTRACT_KEYS = {"input", "samples", "baseline", "effects", "extended", "unexplained", "ambiguous"}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One diagnose run (log with a hidden battery sag) shared by the checks below."""
    from truckd.config.truck import load_config

    p = load_config().vehicle
    d = tmp_path_factory.mktemp("diag")
    write_log(
        d / "log.csv", plant_log(p, with_effect("battery_sag", 0.18), seed=77, n=4000).columns
    )
    write_log(
        d / "val.csv", plant_log(p, with_effect("battery_sag", 0.18), seed=78, n=2000).columns
    )
    code = main(
        [
            "diagnose",
            str(d / "log.csv"),
            "--validate",
            str(d / "val.csv"),
            "--json",
            str(d / "out.json"),
            "--report",
            str(d / "report"),
            "--out",
            str(d / "model.yaml"),
        ]
    )
    assert code == 0
    return d


def test_json_follows_the_contract(run_dir: Path) -> None:
    j = json.loads((run_dir / "out.json").read_text())
    assert CONTRACT_KEYS <= set(j)
    assert j["input"] == "voltage"
    assert j["samples"] == 4000
    for key in ("baseline", "extended"):
        assert {"fit_percent", "rmse", "params"} <= set(j[key])
        assert "force_relerr_percent" not in j[key]
    assert [e["name"] for e in j["effects"]] == ["battery_sag"]
    e = j["effects"][0]
    assert set(e) == {"name", "params", "fit_percent", "fit_gain_percent"}
    assert e["params"]["battery_sag"] == pytest.approx(0.18, rel=0.1)
    assert e["fit_gain_percent"] > 0.5
    # The causes' gains add up to what the extended model gains over the seed, at most
    # (counted from the better of the seed and the joint refit without its causes).
    gains = sum(f["fit_gain_percent"] for f in j["effects"])
    assert gains <= j["extended"]["fit_percent"] - j["baseline"]["fit_percent"] + 1e-9
    assert j["extended"]["fit_percent"] > j["baseline"]["fit_percent"]
    assert j["unexplained"] is False
    assert j["ambiguous"] == []
    # The data's own least squares (WPILib SysId's model), one to one for its users.
    ls = j["least_squares"]
    assert set(ls) == {"kS", "kV", "kA", "kS_se", "kV_se", "kA_se", "fit_percent"}
    assert ls["kV"] > 0 and ls["kA"] > 0 and ls["kV_se"] < ls["kV"]
    assert j["extended"]["fit_percent"] >= ls["fit_percent"]
    # What the speed's noise leaves for any model: the true model (found) reaches it.
    assert j["extended"]["fit_percent"] - 0.5 <= j["fit_ceiling_percent"] < 100.0


def test_model_file_carries_the_effect(run_dir: Path) -> None:
    m = read_model(run_dir / "model.yaml")
    assert m.effects.battery_sag == pytest.approx(0.18, rel=0.1)
    assert m.effects.active() == ("battery_sag",)
    assert "log.csv" in m.source


def test_report_has_plots_and_table(run_dir: Path) -> None:
    index = (run_dir / "report" / "index.html").read_text()
    for png in ("fit.png", "residual.png", "residual_vs.png", "correlation.png"):
        assert (run_dir / "report" / png).stat().st_size > 1000
        assert png in index
    assert "battery_sag" in index and "dead_zone" in index  # the candidates table


def test_extended_model_runs_in_simulate(run_dir: Path) -> None:
    out = run_dir / "sim.csv"
    assert (
        main(
            [
                "simulate",
                str(run_dir / "val.csv"),
                "--out",
                str(out),
                "--model",
                str(run_dir / "model.yaml"),
            ]
        )
        == 0
    )
    assert out.stat().st_size > 0


def test_identify_writes_a_model(tmp_path: Path, params: VehicleParams) -> None:
    log = plant_log(
        params.replace(J_S=params.J_S * 1.3), with_effect("load_force", 0.0), seed=5, n=2500
    )
    write_log(tmp_path / "log.csv", log.columns)
    assert main(["identify", str(tmp_path / "log.csv"), "--out", str(tmp_path / "m.yaml")]) == 0
    m = read_model(tmp_path / "m.yaml")
    assert m.vehicle.J_S == pytest.approx(params.J_S * 1.3, rel=0.05)
    assert m.effects.active() == ()


def _one_line_error(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_missing_speed_column_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t = np.arange(500) * 0.01
    write_log(tmp_path / "bad.csv", {"t": t, "u": np.sin(t)})
    assert main(["diagnose", str(tmp_path / "bad.csv")]) == 2
    line = _one_line_error(capsys)
    assert "bad.csv" in line and "'v'" in line


def test_log_that_determines_nothing_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t = np.arange(500) * 0.01
    write_log(tmp_path / "flat.csv", {"t": t, "u": np.zeros_like(t), "v": t * 0.1})
    assert main(["identify", str(tmp_path / "flat.csv"), "--out", str(tmp_path / "m.yaml")]) == 2
    line = _one_line_error(capsys)
    assert "flat.csv" in line and "0 throughout" in line
    assert not (tmp_path / "m.yaml").exists()


def test_missing_file_is_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["diagnose", str(tmp_path / "nope.csv")]) == 2
    assert "nope.csv" in _one_line_error(capsys)


def test_validation_log_of_another_kind_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    t = np.arange(500) * 0.01
    write_log(tmp_path / "v.csv", {"t": t, "u": np.sin(t), "v": np.sin(t)})
    write_log(tmp_path / "f.csv", {"t": t, "F": np.sin(t), "x": np.cos(t)})
    assert main(["diagnose", str(tmp_path / "v.csv"), "--validate", str(tmp_path / "f.csv")]) == 2
    assert "f.csv" in _one_line_error(capsys)


def test_a_large_log_is_said_before_it_is_read(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Reading a log of tens of megabytes takes seconds: the first line says so (the
    bound lowered here so that a small log stands for a large one)."""
    import truckd.cli.diagnose as cli_diagnose

    monkeypatch.setattr(cli_diagnose, "LARGE_LOG_BYTES", 100)
    t = np.arange(500) * 0.01
    write_log(tmp_path / "big.csv", {"t": t, "u": np.sin(t)})  # refused after reading
    assert main(["diagnose", str(tmp_path / "big.csv")]) == 2
    first = capsys.readouterr().err.splitlines()[0]
    assert first.startswith(f"reading {tmp_path / 'big.csv'} (") and first.endswith(" MB)")
