"""The same simulated truck from every entry point.

``truckd sim`` (one truck and the platoon), ``truckd run --backend sim``, the HIL
firmware process, the HIL platoon world, the emulated board and the benchmarks' setup
each build a simulated truck from a configuration.  Every simulated firmware they build
is caught as it is constructed, and its plant parameters, plant section and firmware
limits are compared with what the configuration says: the plant is ``vehicle`` with
``plant.vehicle`` over it, the encoder has the plant's ticks when it models an encoder
(else the link's), and the range sensor's limits are the estimator's.

The configurations are drawn away from the shipped one (another mass and motor constant
for the plant, other encoder ticks, other range limits), so an entry point that takes
the configured vehicle, the firmware's own 4 m or the link's ticks is caught.
"""

from __future__ import annotations

import dataclasses
import math
import random
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from runtime_support import write_config

from firmware_protocol.codec import encode
from firmware_protocol.messages import MotorCommand
from truckd.cli.main import main
from truckd.config.truck import TruckConfig, load_config
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantConfig
from truckd.runtime.backend import open_backend
from truckd.sim.closed_loop import SimSetup
from truckd.sim.firmware import SimulatedFirmware, constant_speed_lead
from truckd.sim.firmware_main import _handle, serve_truck
from truckd.sim.platoon import make_platoon_scenario
from truckd.sim.platoon_world import World
from truckd.sim.truck import build_truck, emulated_board, truck_spec

Built = tuple[VehicleParams, PlantConfig, int, float, float]
"""(plant parameters, plant section, encoder ticks/rev, range min m, range max m)."""


def _overrides(rng: random.Random) -> dict[str, Any]:
    """A configuration away from the shipped one: the plant is another truck than the
    configured one, the encoder and the range sensor have other limits."""
    plant: dict[str, Any] = {
        "vehicle": {"m": round(rng.uniform(1.5, 4.0), 3), "K_T": round(rng.uniform(0.004, 0.02), 5)}
    }
    if rng.random() < 0.5:
        plant["encoder_ticks_per_rev"] = rng.choice((256, 1000, 2048))
    return {
        "plant": plant,
        "link": {"encoder_ticks_per_rev": rng.choice((64, 300, 1024))},
        "control": {
            "estimator": {
                "range_max": round(rng.uniform(1.5, 12.0), 2),
                "range_min": round(rng.uniform(0.0, 0.1), 3),
            }
        },
    }


def _expected(cfg: TruckConfig) -> Built:
    """What the configuration says, from its keys (not through the factory)."""
    vehicle = dataclasses.replace(cfg.vehicle, **cfg.plant.vehicle.given())
    ticks = cfg.plant.encoder_ticks_per_rev or cfg.link.encoder_ticks_per_rev
    est = cfg.control.estimator
    return vehicle, cfg.plant, ticks, est.range_min, est.range_max


PLATOON_DELAY = make_platoon_scenario("platoon-brake").input_delay
"""The platoon scenarios add their actuation delay to the plant (the larger one holds)."""


def _with_delay(b: Built, delay: float) -> Built:
    eff = b[1].effects
    plant = dataclasses.replace(
        b[1], effects=dataclasses.replace(eff, input_delay=max(eff.input_delay, delay))
    )
    return b[0], plant, *b[2:]


def _built(fw: SimulatedFirmware) -> Built:
    c = fw.cfg
    return fw.plant.p, fw.plant.cfg, c.ticks_per_rev, c.range_min, c.range_max


@pytest.fixture
def caught(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[SimulatedFirmware]]:
    """Every simulated firmware constructed while the test runs."""
    seen: list[SimulatedFirmware] = []
    init = SimulatedFirmware.__init__

    def spy(self: SimulatedFirmware, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        seen.append(self)

    monkeypatch.setattr(SimulatedFirmware, "__init__", spy)
    yield seen


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_every_entry_point_builds_the_configured_truck(
    seed: int,
    tmp_path: Path,
    caught: list[SimulatedFirmware],
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = write_config(tmp_path / "truck.yaml", _overrides(random.Random(seed)))
    cfg = load_config(path)
    want = _expected(cfg)
    assert want[0] != cfg.vehicle  # the plant is not the configured truck
    lead = constant_speed_lead(2.0, 1.0)
    by_entry: dict[str, list[Built]] = {}

    def entry(name: str) -> None:
        by_entry[name] = [_built(fw) for fw in caught]
        caught.clear()

    args = ["sim", "--config", str(path), "--duration", "0.05"]
    assert main([*args, "--scenario", "follow"]) == 0
    entry("truckd sim")
    platoon = ["--scenario", "platoon-brake", "--platoon", "2", "--duration", "1"]
    assert main([*args[:3], *platoon]) == 0
    entry("truckd sim --platoon")
    capsys.readouterr()

    backend = open_backend("sim", cfg, cfg.control)
    backend.close()
    entry("truckd run --backend sim")

    for link in ("serial", "slcan"):
        fw = serve_truck(cfg, lead, link, str(tmp_path / f"tty-{link}"))
        fw.link.close()
        entry(f"HIL firmware ({link})")

    world = World(tmp_path, 2, 1.0, str(path))
    world.close()
    entry("HIL platoon world")

    # the benchmarks' setup: SimSetup.from_config, run as truckd sim runs it
    setup = SimSetup.from_config(cfg)
    assert (setup.truck.vehicle, setup.truck.plant) == want[:2]
    f = setup.truck.firmware
    assert (f.ticks_per_rev, f.range_min, f.range_max) == want[2:]

    assert set(by_entry) == {
        "truckd sim",
        "truckd sim --platoon",
        "truckd run --backend sim",
        "HIL firmware (serial)",
        "HIL firmware (slcan)",
        "HIL platoon world",
    }
    for name, trucks in by_entry.items():
        assert trucks, name
        for truck in trucks:
            assert truck == (
                _with_delay(want, PLATOON_DELAY) if name.endswith("--platoon") else want
            ), name


def test_the_emulated_board_has_the_configured_truck(tmp_path: Path) -> None:
    """Processor in the loop: the host side's plant and sensor limits (not started)."""
    path = write_config(tmp_path / "truck.yaml", _overrides(random.Random(7)))
    cfg = load_config(path)
    vehicle, plant, ticks, _lo, hi = _expected(cfg)
    board = emulated_board(truck_spec(cfg), constant_speed_lead(2.0, 1.0), tmp_path / "tty")
    assert (board.plant.p, board.plant.cfg, board.range_max) == (vehicle, plant, hi)
    # encoder counts per metre of the configured ticks on the plant's wheel
    ticks_per_m = board._ticks_per_m
    assert math.isclose(ticks_per_m, ticks / (2.0 * math.pi * vehicle.r_w))


def test_status_reports_the_last_command_before_and_after_the_first() -> None:
    """The HIL firmware process's ``status`` (the contract: ``last_command`` with ``voltage``
    and ``enable``): before any command, what the firmware holds (0 V, disabled), never
    null; after one, that command."""
    truck = build_truck(truck_spec(load_config()), constant_speed_lead(1.0, 0.0))
    reply, stop = _handle(truck.firmware, {"cmd": "status"})
    assert reply["ok"] and not stop
    assert reply["last_command"] == {"voltage": 0.0, "enable": False}
    assert truck.link is not None
    truck.link.send(encode(MotorCommand(2.5, True), 1))
    truck.firmware.step(0.01)
    after, _ = _handle(truck.firmware, {"cmd": "status"})
    assert after["last_command"] == {"voltage": 2.5, "enable": True}, after["last_command"]
