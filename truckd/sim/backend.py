"""The daemon's ``sim`` backend: the simulated firmware and plant on an in-process link,
the lead driving the ``follow`` scenario.  Loaded by name from
:func:`truckd.runtime.backend.open_backend` only when ``sim`` is asked for."""

from __future__ import annotations

from truckd.config.truck import TruckConfig
from truckd.control.config import ControlConfig
from truckd.io.link import Link
from truckd.sim.firmware import FirmwareSimConfig, SimulatedFirmware, simulated_truck
from truckd.sim.plant import Plant
from truckd.sim.scenarios import World, make_scenario


def open_sim(
    cfg: TruckConfig, control: ControlConfig, ticks_per_rev: int
) -> tuple[Link, SimulatedFirmware]:
    """(companion link, firmware to advance after each command)."""
    plant = Plant(cfg.plant_vehicle, cfg.plant)
    world = World(make_scenario("follow", cfg.vehicle, control))
    link, fw, _wire = simulated_truck(
        plant, world.range_fn, "frames", FirmwareSimConfig(ticks_per_rev=ticks_per_rev)
    )
    return link, fw
