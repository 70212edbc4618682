"""`truckd characterize` in process on the ``sim`` backend (the daemon's own loop and the C
firmware core, in simulated time) on drawn trucks NOT the configured one: motor constant
and mass 2-5x off, a driver's dead zone or a battery's sag hidden (characterize_support).

Pass: exit 0, the truck at rest at the end, short of the wall ahead; what
:func:`characterize_support.assert_found` requires (the hidden effect named; kS, kV, kA
and the effect within 10 %, a poorly determined kS within 50 %; the diagnosed model keeps
the gap better than the configured one on the true plant).  The same drawn trucks' input
delay and load over real links, in real time: tests/test_hil_characterize.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from characterize_support import DRAWN_DRIVE, WALL_M, Track, assert_found, draw_truck
from runtime_support import write_config

from truckd.cli.characterize import characterize
from truckd.config.truck import load_config
from truckd.runtime.ratekeeper import SteppedClock

pytestmark = pytest.mark.slow

IN_PROCESS = {"backend": "sim", "realtime": False, "telemetry": {"enabled": False}}
"""The ``runtime:`` section: no SCHED_FIFO for pytest (every later test would inherit it),
nothing on the network."""


@pytest.mark.parametrize(("seed", "effect"), [(37, "dead_zone"), (41, "battery_sag")])
def test_characterize_finds_a_drawn_trucks_hidden_effect(
    tmp_path: Path, seed: int, effect: str
) -> None:
    configured = load_config()
    truck = draw_truck(seed, configured.vehicle, effect)
    plant_cfg = write_config(tmp_path / "plant.yaml", {"plant": truck.plant_section()})
    cfg = load_config(
        write_config(
            tmp_path / "truck.yaml",
            {"plant": truck.plant_section(), "characterize": DRAWN_DRIVE, "runtime": IN_PROCESS},
        )
    )
    wall = Track(WALL_M)
    lines: list[str] = []
    out = tmp_path / "out"
    code = characterize(cfg, "sim", out, lines.append, wall.prepare, SteppedClock())
    assert code == 0, lines
    assert wall.fw is not None and abs(wall.fw.plant.v) < 1e-3  # at rest at the end
    margin = cfg.characterize.wall_margin_m
    assert wall.x_max < WALL_M - margin, (wall.x_max, WALL_M, margin)
    assert json.loads((out / "summary.json").read_text())["completed"] is True
    period_s = 1.0 / cfg.control.rate_hz
    assert_found(truck, out, configured.vehicle, period_s, plant_cfg,
                 DRAWN_DRIVE["closed_loop_scenarios"])  # fmt: skip
