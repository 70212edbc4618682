"""The daemon's ``sim`` backend: the configuration's simulated truck
(:func:`truckd.sim.truck.truck_spec`) on an in-process link, the lead driving the
``follow`` scenario.  Registered by name in :data:`truckd.io.backends.BACKENDS` and
imported only when ``sim`` is asked for."""

from __future__ import annotations

from truckd.config.truck import TruckConfig
from truckd.control.config import ControlConfig
from truckd.io.devlock import DeviceLock
from truckd.io.link import Link
from truckd.runtime.backend import Backend, Clock
from truckd.sim.firmware import SimulatedFirmware
from truckd.sim.scenarios import World, make_scenario
from truckd.sim.truck import build_truck, truck_spec


class SimBackend(Backend):
    """The simulated truck; :meth:`tick` advances its firmware and plant."""

    name = "sim"

    def __init__(
        self, link: Link, firmware: SimulatedFirmware, lock: DeviceLock | None = None
    ) -> None:
        super().__init__(link, lock)
        self.firmware = firmware
        """The simulated firmware (its ``range_fn`` and faults can be changed)."""

    @classmethod
    def open(
        cls,
        cfg: TruckConfig,
        control: ControlConfig,
        clock: Clock,
        lock: DeviceLock | None,
    ) -> SimBackend:
        """The truck of ``cfg``; ``control`` is the daemon's (the lead's scenario)."""
        world = World(make_scenario("follow", cfg.vehicle, control))
        truck = build_truck(truck_spec(cfg), world.range_fn)
        assert truck.link is not None
        return cls(truck.link, truck.firmware, lock)

    def tick(self, dt: float) -> None:
        self.firmware.step(dt)
