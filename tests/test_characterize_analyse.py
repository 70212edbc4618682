"""`truckd characterize --drive-only`, then `--analyse DIR` (in process, the ``sim``
backend in simulated time): the drive leaves log.csv and summary.json (``analysed``
false, no model); the analysis of that directory afterwards writes the model, the
diagnosis and the report (the simulated truck's feedforward constants); a directory
without a completed drive, or driving options beside ``--analyse``, are one line and
exit 2."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from characterize_support import feedforward
from runtime_support import write_config

from truckd.cli.characterize import analyse_dir, characterize
from truckd.cli.main import main
from truckd.config.truck import load_config
from truckd.runtime.ratekeeper import SteppedClock

pytestmark = pytest.mark.slow

SHORT = {"quasistatic_duration_s": 3.0, "step_voltages": [2.0, 4.0], "step_duration_s": 1.0,
         "validation_duration_s": 2.0, "closed_loop_scenarios": []}  # fmt: skip
"""Experiments long enough to analyse, no closed-loop comparison (its own test is HIL)."""


def _config(tmp: Path) -> Path:
    return write_config(
        tmp / "truck.yaml",
        {"characterize": SHORT,
         "runtime": {"backend": "sim", "realtime": False, "telemetry": {"enabled": False}}},
    )  # fmt: skip


def _drive(tmp: Path, out: str, drive_only: bool) -> tuple[int, list[str]]:
    lines: list[str] = []
    cfg = load_config(_config(tmp))
    code = characterize(cfg, "sim", tmp / out, lines.append, None, SteppedClock(), drive_only)
    return code, lines


def _summary(d: Path) -> dict[str, Any]:
    return json.loads((d / "summary.json").read_text())  # type: ignore[no-any-return]


def test_drive_only_then_analyse_finds_the_truck(tmp_path: Path) -> None:
    code, lines = _drive(tmp_path, "later", drive_only=True)
    later = tmp_path / "later"
    assert code == 0
    driven = _summary(later)
    assert driven["completed"] and driven["analysed"] is False and "feedforward" not in driven
    assert not (later / "model.yaml").exists() and (later / "log.csv").stat().st_size > 0
    assert any("--analyse" in ln for ln in lines)

    said: list[str] = []
    assert analyse_dir(load_config(_config(tmp_path)), later, said.append) == 0
    analysed = _summary(later)
    assert analysed["analysed"] is True
    for name in ("model.yaml", "diagnosis.json", "report.html"):
        assert (later / name).stat().st_size > 0
    assert analysed["experiments"] == driven["experiments"]
    assert analysed["checks"] == driven["checks"]

    # the simulated truck is the configured one: its feedforward constants come back
    for k, want in feedforward(load_config().vehicle).items():
        assert analysed["feedforward"][k] == pytest.approx(want, rel=0.1), k


def test_analyse_refuses_what_is_not_a_completed_drive(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = str(_config(tmp_path))
    assert main(["characterize", "--config", cfg, "--analyse", str(tmp_path / "none")]) == 2
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    (stopped / "summary.json").write_text(json.dumps({"completed": False, "exit_code": 4}))
    assert main(["characterize", "--config", cfg, "--analyse", str(stopped)]) == 2
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    (garbled / "summary.json").write_text('{"completed": true}')
    assert main(["characterize", "--config", cfg, "--analyse", str(garbled)]) == 2
    argv = ["characterize", "--config", cfg, "--analyse", str(stopped), "--backend", "sim"]
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 4, err
    assert "summary.json" in err[0] and "did not complete (exit 4)" in err[1]
    assert "not a characterize summary" in err[2] and "drives nothing" in err[3]
    assert all(line.startswith("truckd characterize: error: ") for line in err), err
    assert not any((d / "model.yaml").exists() for d in (stopped, garbled))
