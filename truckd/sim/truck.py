"""The one factory of the simulated truck: plant, simulated firmware and sensors, with
their limits taken from one configuration.

Every caller builds its simulated truck here: ``truckd sim`` and the platoon world (through
:class:`~truckd.sim.closed_loop.SimSetup`), the daemon's ``sim`` backend, the HIL firmware
process (:mod:`truckd.sim.firmware_main`), the HIL platoon world, the emulated board
(:mod:`truckd.sim.pil`) and the benchmarks.  What they share is a :class:`TruckSpec`:

- the plant's truth: ``vehicle`` with ``plant.vehicle`` over it (the simulated truck may
  differ from the one the controller believes in) and the ``plant:`` section;
- the sensors' limits the firmware applies: encoder ticks per revolution (the plant's
  encoder when it models one, else the link's) and the range sensor's minimum and maximum
  range, the ones the estimator is configured with (``control.estimator.range_min`` and
  ``range_max``): the configuration describes one sensor, so the simulated one has the
  limits the daemon expects of it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from truckd.control.config import ControlConfig
from truckd.io.inproc import Wire, inproc_pair
from truckd.io.link import Link
from truckd.model.params import VehicleParams
from truckd.model.plant_config import PlantConfig, encoder_ticks_per_rev
from truckd.sim.firmware import FirmwareSimConfig, RangeFn, SimulatedFirmware
from truckd.sim.pil import EmulatedBoard
from truckd.sim.plant import Plant
from truckd.sim.pty_link import PtyDevice
from truckd.sim.slcan_peer import SlcanDevice

if TYPE_CHECKING:
    from truckd.config.truck import TruckConfig

Device = PtyDevice | SlcanDevice
"""A device the firmware serves to a daemon in another process (pty, simulated slcan)."""


def firmware_config(
    plant: PlantConfig, control: ControlConfig, link_ticks: int
) -> FirmwareSimConfig:
    """The simulated firmware's sensors: encoder ticks per revolution (the plant's encoder
    when it models one, else ``link_ticks``) and the estimator's range limits."""
    est = control.estimator
    return FirmwareSimConfig(
        ticks_per_rev=encoder_ticks_per_rev(plant.encoder_ticks_per_rev, link_ticks),
        range_min=est.range_min,
        range_max=est.range_max,
    )


@dataclass(frozen=True)
class TruckSpec:
    """What makes one simulated truck (see module docstring)."""

    vehicle: VehicleParams
    """The plant's parameters (the truth, not the controller's belief)."""
    plant: PlantConfig
    firmware: FirmwareSimConfig

    @classmethod
    def of(
        cls,
        vehicle: VehicleParams,
        plant: PlantConfig,
        control: ControlConfig,
        link_ticks: int,
        firmware: FirmwareSimConfig | None = None,
    ) -> TruckSpec:
        """A truck from its parts; ``firmware`` replaces the one the parts give."""
        return cls(vehicle, plant, firmware or firmware_config(plant, control, link_ticks))

    def new_plant(self, v0: float = 0.0, x0: float = 0.0, t0: float = 0.0) -> Plant:
        """A fresh plant at speed ``v0`` (m/s) and position ``x0`` (m), its clock at ``t0``
        (s)."""
        plant = Plant(self.vehicle, self.plant)
        plant.reset(v=v0)
        plant.x = x0
        plant.t = t0
        return plant


def truck_spec(cfg: TruckConfig) -> TruckSpec:
    """The simulated truck of a configuration."""
    return TruckSpec.of(cfg.plant_vehicle, cfg.plant, cfg.control, cfg.link.encoder_ticks_per_rev)


@dataclass
class SimTruck:
    """A built simulated truck: its plant, the firmware on it, and the daemon's end of an
    in-process link (``link``, ``wire``; None when the firmware serves a :data:`Device`,
    then ``firmware.link`` is that device)."""

    plant: Plant
    firmware: SimulatedFirmware
    link: Link | None
    wire: Wire | None


def build_truck(
    spec: TruckSpec,
    range_fn: RangeFn,
    *,
    mode: Literal["frames", "bytes"] = "frames",
    device: Callable[[Callable[[], float]], Device] | None = None,
    v0: float = 0.0,
    x0: float = 0.0,
    t0: float = 0.0,
) -> SimTruck:
    """Build the truck of ``spec`` at speed ``v0`` and position ``x0``, the plant's clock
    at ``t0`` (s; the firmware's clock starts at 0 there).

    Without ``device`` the firmware sits on an in-process pair (``mode``: CAN frames or the
    serial byte stream; the disconnect fault unplugs the wire).  With it, the firmware
    serves ``device(clock)``, opened on the plant's clock.  Drive it with
    ``firmware.step(dt)``."""
    plant = spec.new_plant(v0, x0, t0)
    if device is not None:
        dev = device(lambda: plant.t)
        fw = SimulatedFirmware(plant, range_fn, dev, spec.firmware, dev.unplug, dev.replug)
        return SimTruck(plant, fw, None, None)
    companion, mcu, wire = inproc_pair(mode)
    fw = SimulatedFirmware(plant, range_fn, mcu, spec.firmware, wire.disconnect, wire.reconnect)
    return SimTruck(plant, fw, companion, wire)


def emulated_board(
    spec: TruckSpec,
    range_fn: RangeFn,
    link_path: str | Path,
    *,
    v0: float = 0.0,
    elf: Path | None = None,
    qemu: str = "qemu-system-arm",
) -> EmulatedBoard:
    """The truck of ``spec`` on the emulated board (processor in the loop, not started):
    the plant and the sensor limits the host side applies are the spec's."""
    return EmulatedBoard(
        spec.new_plant(v0),
        range_fn,
        link_path,
        ticks_per_rev=spec.firmware.ticks_per_rev,
        range_max=spec.firmware.range_max,
        range_noise=spec.firmware.range_noise,
        seed=spec.firmware.seed,
        elf=elf,
        qemu=qemu,
    )
