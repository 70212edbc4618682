"""`truckd characterize` bring-up checks, in process on the ``sim`` backend (the daemon's own
loop in simulated time, the simulated firmware wired the wrong way round through
``plant.wiring``/``plant.vehicle``, or a wall too close): each failure stops the routine
with exit 3 and one line that says what to fix, and the simulated truck ends at rest
without having driven into anything.  The runs that pass their checks and analyse skip
the closed-loop comparison (`closed_loop_scenarios: []`: half their time;
tests/test_hil_characterize.py checks it)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
from characterize_support import Track
from runtime_support import write_config

from truckd.config.truck import load_config
from truckd.runtime.backend import Backend
from truckd.runtime.ratekeeper import SteppedClock

pytestmark = pytest.mark.slow


def run(
    tmp_path: Path,
    plant: dict[str, Any] | None = None,
    wall: float | None = 3.5,
    fault: dict[str, Any] | None = None,
    characterize: dict[str, Any] | None = None,
) -> tuple[int, dict[str, Any], list[str], Track]:
    from truckd.cli.characterize import characterize as run_characterize

    cfg = load_config(
        write_config(
            tmp_path / "truck.yaml",
            {
                "plant": plant or {},
                "characterize": characterize or {},
                # in this process: no SCHED_FIFO for pytest (every later test would inherit it)
                "runtime": {"backend": "sim", "realtime": False, "telemetry": {"enabled": False}},
            },
        )
    )
    track = Track(wall)
    lines: list[str] = []

    def prepare(backend: Backend) -> None:
        track.prepare(backend)
        if fault is not None:
            assert backend.firmware is not None
            backend.firmware.apply_fault(fault)

    # in simulated time: the checks judge rates and ages, the same on a busy machine
    code = run_characterize(cfg, "sim", tmp_path / "out", lines.append, prepare, SteppedClock())
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    return code, summary, lines, track


def failed(summary: dict[str, Any]) -> list[dict[str, Any]]:
    return [c for c in summary["checks"] if not c["ok"]]


def at_rest(track: Track) -> None:
    assert track.fw is not None
    assert abs(track.fw.plant.v) < 1e-3
    assert not track.fw.enabled or track.fw.voltage == 0.0


@pytest.mark.parametrize(
    ("wiring", "name", "fix"),
    [
        ({"motor_sign": -1}, "motor_polarity", "swap the motor leads"),
        ({"encoder_sign": -1}, "encoder_direction", "swap the encoder's A and B channels"),
        ({"counts_scale": 2.0}, "counts_per_metre", "link.encoder_ticks_per_rev 512"),
    ],
)
def test_a_truck_wired_the_wrong_way_round_fails_its_check(
    tmp_path: Path, wiring: dict[str, Any], name: str, fix: str
) -> None:
    code, summary, lines, track = run(tmp_path, plant={"wiring": wiring})
    assert code == 3
    bad = failed(summary)
    assert [c["name"] for c in bad] == [name]
    assert fix in bad[0]["detail"]
    assert "\n" not in bad[0]["detail"]
    if name == "counts_per_metre":  # the ratio measured against the range sensor
        ratio = float(re.search(r"\(([0-9.]+)x\)", bad[0]["detail"]).group(1))  # type: ignore[union-attr]
        assert 1.8 < ratio < 2.2
    assert any(name in ln and fix in ln for ln in lines)
    assert not (tmp_path / "out" / "model.yaml").exists()
    assert summary["experiments"][0]["t_start"] is None  # nothing driven beyond the pulse
    assert summary["distance_m"] < 0.5
    at_rest(track)


@pytest.mark.parametrize("wiring", [{"motor_sign": -1}, {"encoder_sign": -1}])
def test_without_a_target_ahead_a_reversed_motor_or_encoder_fails_and_asks_for_one(
    tmp_path: Path, wiring: dict[str, Any]
) -> None:
    """Nothing ahead within the range sensor's reach: the counts fall either way, and
    nothing else the truck measures tells a swapped motor from a swapped encoder (the
    motor's current follows its own terminal voltage either way), so the one line names
    both and asks for a target ahead."""
    code, summary, lines, track = run(tmp_path, plant={"wiring": wiring}, wall=None)
    assert code == 3
    bad = failed(summary)
    assert [c["name"] for c in bad] == ["motor_polarity"]
    detail = bad[0]["detail"]
    assert "motor leads or the encoder channels are swapped" in detail
    assert "put a target" in detail and "\n" not in detail
    assert any(detail in ln for ln in lines)
    assert summary["experiments"][0]["t_start"] is None
    assert summary["distance_m"] < 0.5
    at_rest(track)


def test_the_right_wiring_passes_every_check(tmp_path: Path) -> None:
    """The counterpart of the failures above (same world, wired right): every check passes
    and the experiments start (stopped early by a short track, to stay fast)."""
    code, summary, _lines, track = run(
        tmp_path,
        characterize={"quasistatic_duration_s": 0.5, "step_voltages": [1.0],
                      "step_duration_s": 0.3, "validation_duration_s": 0.5,
                      "closed_loop_scenarios": []},
    )  # fmt: skip
    assert [c["name"] for c in failed(summary)] == []
    names = {c["name"] for c in summary["checks"]}
    assert {"motor_polarity", "encoder_direction", "counts_per_metre", "battery", "range"} <= names
    assert all(e["t_start"] is not None for e in summary["experiments"])
    assert code in (0, 1)  # the analysis of so short a log may refuse; the checks passed
    at_rest(track)


def test_low_battery_fails_before_the_truck_moves(tmp_path: Path) -> None:
    code, summary, _lines, track = run(tmp_path, plant={"vehicle": {"V_batt": 5.4}})
    assert code == 3
    bad = failed(summary)
    assert [c["name"] for c in bad] == ["battery"]
    assert "5.40 V is below 6 V" in bad[0]["detail"] and "charge or swap" in bad[0]["detail"]
    assert summary["distance_m"] < 1e-3
    at_rest(track)


def test_no_range_reading_fails(tmp_path: Path) -> None:
    code, summary, _lines, track = run(
        tmp_path, fault={"fault": "drop", "message": "RANGE", "count": -1}
    )
    assert code == 3
    bad = failed(summary)
    assert [c["name"] for c in bad] == ["range"]
    assert "no range reading" in bad[0]["detail"]
    assert summary["distance_m"] < 1e-3
    at_rest(track)


def test_a_wall_closer_than_the_budget_is_refused(tmp_path: Path) -> None:
    """Default budget 0.8 m and margin 0.3 m: a wall 0.9 m ahead leaves 0.6 m."""
    code, summary, _lines, track = run(tmp_path, wall=0.9)
    assert code == 3
    bad = failed(summary)
    assert [c["name"] for c in bad] == ["free_space"]
    assert "0.60 m to drive" in bad[0]["detail"] and "clear the" in bad[0]["detail"]
    assert track.x_max < 1e-3
    at_rest(track)


def test_a_wall_within_the_track_shortens_the_experiments(tmp_path: Path) -> None:
    """A wall 1.6 m ahead on a 3 m track: the forward experiments end at the budget, and
    the truck never comes nearer the wall than the margin."""
    code, summary, _lines, track = run(
        tmp_path,
        wall=1.6,
        characterize={"quasistatic_ramp_v_per_s": 1.5, "quasistatic_duration_s": 3.0,
                      "step_voltages": [3.0], "step_duration_s": 2.0,
                      "validation_duration_s": 0.5, "closed_loop_scenarios": []},
    )  # fmt: skip
    exps = {e["name"]: e for e in summary["experiments"]}
    assert exps["quasistatic-forward"]["ended"] == "distance budget"
    assert exps["dynamic-forward-3V"]["ended"] == "distance budget"
    assert track.x_max < 1.6 - 0.3 + 0.02
    assert code in (0, 1)
    at_rest(track)


def test_bad_input_is_one_line_and_nothing_moves(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from truckd.cli.main import main

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "log.csv").write_text("t,u,v\n")
    cfg = write_config(tmp_path / "truck.yaml", {"runtime": {"backend": "sim"}})
    assert main(["characterize", "--config", str(cfg), "--out", str(busy)]) == 2
    err = capsys.readouterr().err
    assert "is not an empty directory" in err and err.count("\n") == 1
    assert sorted(p.name for p in busy.iterdir()) == ["log.csv"]
    for key, value, said in (
        ("speed_limit_m_s", -1.0, "'characterize.speed_limit_m_s' = -1.0"),
        ("validation_v", 0.05, "validation_v (0.05) must be 0 (the highest step) or >= 0.1"),
    ):
        bad = write_config(tmp_path / "bad.yaml", {"characterize": {key: value}})
        assert main(["characterize", "--config", str(bad), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err
        assert said in err and err.count("\n") == 1
        assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("section", "amplitude"),
    [({}, 3.0), ({"step_voltages": [2.0, 4.5]}, 4.5), ({"validation_v": 2.5}, 2.5)],
)
def test_the_validation_chirp_reaches_the_highest_step_unless_set(
    tmp_path: Path, section: dict[str, Any], amplitude: float
) -> None:
    """The chirp validates the effects the steps excite: by default its amplitude is the
    highest step voltage (a battery's sag, a current limit act at a high duty only)."""
    from truckd.runtime.characterize_plan import plan_experiments

    cfg = load_config(write_config(tmp_path / "truck.yaml", {"characterize": section}))
    chirp = [e for e in plan_experiments(cfg.characterize) if e.kind == "validation"]
    assert len(chirp) == 1
    peak = max(
        abs(chirp[0].voltage(k * 0.001, cfg.characterize))
        for k in range(int(chirp[0].duration_s / 0.001))
    )
    assert peak == pytest.approx(amplitude, rel=1e-3)
