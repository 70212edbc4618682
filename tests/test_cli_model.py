"""`truckd params` and `truckd simulate` through the real entry point."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from truckd.cli.main import main
from truckd.config.truck import load_config
from truckd.errors import InputError
from truckd.logfile import read_log, write_log
from truckd.model.effects import Effects
from truckd.model.motor import steady_speed
from truckd.model.params import VehicleParams
from truckd.modelfile import ModelFile, read_model, write_model

CONTRACT_KEYS = {
    "R_m",
    "L_m",
    "K_v",
    "K_T",
    "J_S",
    "n_g",
    "n_fd",
    "r_w",
    "m",
    "K_coulomb",
    "K_stiction",
}


def test_params_json_has_the_contract_keys(
    capsys: pytest.CaptureFixture[str], params: VehicleParams
) -> None:
    assert main(["params", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert CONTRACT_KEYS <= set(out)
    assert out["K_T"] == params.K_T and out["r_w"] == params.r_w


def test_console_script_runs() -> None:
    exe = Path(sys.executable).parent / "truckd"
    res = subprocess.run(
        [str(exe), "params", "--json"], capture_output=True, text=True, check=False
    )
    assert res.returncode == 0, res.stderr
    assert CONTRACT_KEYS <= set(json.loads(res.stdout))


def test_simulate_writes_the_log_format(tmp_path: Path, params: VehicleParams) -> None:
    t = np.arange(0.0, 3.0, 0.01)
    src = tmp_path / "in.csv"
    write_log(src, {"u": np.full_like(t, 5.0), "t": t, "note": np.arange(len(t))})
    out = tmp_path / "out.csv"
    assert main(["simulate", str(src), "--out", str(out)]) == 0
    log = read_log(out)
    assert {"t", "u", "v", "i", "x", "note"} <= set(log.columns)
    assert log["v"][-1] == pytest.approx(params.speed(steady_speed(params, 5.0)), rel=0.005)
    np.testing.assert_array_equal(log["note"], np.arange(len(t)))


def test_simulate_with_model_file_uses_its_effects(tmp_path: Path, params: VehicleParams) -> None:
    t = np.arange(0.0, 3.0, 0.01)
    src = tmp_path / "in.csv"
    write_log(src, {"t": t, "u": np.full_like(t, 6.0)})
    model = tmp_path / "model.yaml"
    from truckd.model.effects import Effects

    write_model(model, ModelFile(vehicle=params, effects=Effects(voltage_saturation=3.0)))
    out = tmp_path / "out.csv"
    assert main(["simulate", str(src), "--out", str(out), "--model", str(model)]) == 0
    v_end = read_log(out)["v"][-1]
    assert v_end == pytest.approx(params.speed(steady_speed(params, 3.0)), rel=0.005)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("t,v\n0,0\n0.01,0\n", "missing column 'u'"),
        ("t;u\n0;0\n0.01;1\n", "the file looks separated by ';': expected commas"),
        ("Time,u\n0,0\n0.01,1\n", "did you mean 'Time'? columns are named exactly 't'"),
        ("t [s],u\n0,0\n0.01,1\n", "did you mean 't [s]'?"),
        ("Timestamp,Name,Value\n0,/a,1\n", "a WPILib DataLog export"),
        ("t,u\n0,0\n0.01,abc\n", "line 3: column 'u': 'abc' is not a number"),
        ("t,u\n0,0\n0.01,1\n0.01,2\n", "line 4: time t=0.01 does not increase"),
        ("t,u\n0,0\n0.01,1,5\n", "line 3: 3 cells, header has 2"),
        ("t,u\n0,nan\n0.01,1\n", "line 2: column 'u': 'nan' is not finite"),
        ("", "empty file"),
        ("t,u\n", "no data rows"),
    ],
)
def test_simulate_rejects_malformed_csv_with_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, expected: str
) -> None:
    src = tmp_path / "bad.csv"
    src.write_text(text)
    assert main(["simulate", str(src), "--out", str(tmp_path / "o.csv")]) == 2
    err = capsys.readouterr().err
    assert expected in err and str(src) in err
    assert not (tmp_path / "o.csv").exists()


def test_bad_usage_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["simulate"]) == 2  # usage error: a return code, one line
    assert len(capsys.readouterr().err.splitlines()) == 1
    assert main(["params", "--config", "/nonexistent/truck.yaml"]) == 2
    capsys.readouterr()
    # an option the command does not have: named by that command (reference section 1)
    assert main(["replay", "x.csv", "--config", "c.yaml"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("truckd replay: error: unrecognized arguments: --config c.yaml"), line
    assert main(["--bogus", "params", "--json"]) == 2  # given to truckd, named by truckd
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("truckd: error: unrecognized arguments: --bogus"), line


def test_logs_after_an_option_are_logs_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``identify A --out m.yaml B``: a plain argument after the options joins the
    command's list of logs (argparse alone stopped the list at the first option); a
    command without such a list still refuses it."""
    t = np.arange(0.0, 3.0, 0.01)
    for name, volts in (("a", 4.0), ("b", -3.0)):
        write_log(tmp_path / f"in-{name}.csv", {"t": t, "u": np.where(t > 0.2, volts, 0.0)})
        assert main(["simulate", str(tmp_path / f"in-{name}.csv"), "--out",
                     str(tmp_path / f"{name}.csv")]) == 0  # fmt: skip
    capsys.readouterr()
    a, b, model = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "m.yaml"
    assert main(["identify", str(a), "--out", str(model), str(b)]) == 0
    assert f"identified {a} {b}:" in capsys.readouterr().out
    assert main(["params", "--json", "extra"]) == 2


def test_a_model_with_numpy_values_is_written_and_reads_back(tmp_path: Path) -> None:
    """Fitted values arrive as numpy scalars; the model file holds them as plain numbers."""
    p = load_config().vehicle
    fitted = p.replace(J_S=np.float64(p.J_S * 2.0))
    eff = Effects(load_force=np.float64(-0.22), input_delay=np.float64(0.03))
    write_model(tmp_path / "m.yaml", ModelFile(vehicle=fitted, effects=eff))
    back = read_model(tmp_path / "m.yaml")
    assert back.vehicle.J_S == float(fitted.J_S)
    assert back.effects.load_force == -0.22 and back.effects.input_delay == 0.03


def test_a_model_whose_truck_cannot_move_is_refused(tmp_path: Path) -> None:
    """A saturation of a millivolt or a dead zone above the battery leave nothing that
    breaks the truck away: the model file is refused when read, naming why."""
    p = load_config().vehicle
    for eff in (Effects(voltage_saturation=0.001), Effects(dead_zone=p.V_batt + 0.5)):
        write_model(tmp_path / "m.yaml", ModelFile(vehicle=p, effects=eff))
        with pytest.raises(InputError, match="this model's truck cannot move"):
            read_model(tmp_path / "m.yaml")
    write_model(tmp_path / "m.yaml", ModelFile(vehicle=p, effects=Effects(dead_zone=0.3)))
    assert read_model(tmp_path / "m.yaml").effects.dead_zone == 0.3
