"""The daemon's link to the microcontroller, by backend name.

``serial`` and ``can`` open the real transports (truckd.io, settings in ``link:``);
``sim`` puts the simulated firmware and plant on an in-process link and advances them
by one control period per cycle, in real time (the lead drives the ``follow`` scenario).
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from truckd.config.truck import TruckConfig
from truckd.control.config import ControlConfig
from truckd.io import open_link
from truckd.io.link import Link

if TYPE_CHECKING:
    from truckd.sim.firmware import SimulatedFirmware

SIM_BACKEND = "truckd.sim.backend"
"""The module of the ``sim`` backend, imported only when asked for by name (as python-can
loads its interfaces): ``truckd run`` on the car never loads the plant or the scenarios."""


@dataclass
class Backend:
    """A link plus, for ``sim``, the firmware to advance after each command."""

    name: str
    link: Link
    firmware: SimulatedFirmware | None = None

    def tick(self, dt: float) -> None:
        """Advance the simulated truck by ``dt`` s (no-op on real hardware)."""
        if self.firmware is not None:
            self.firmware.step(dt)

    def close(self) -> None:
        self.link.close()


def open_backend(
    name: str,
    cfg: TruckConfig,
    control: ControlConfig,
    ticks_per_rev: int,
    clock: Callable[[], float] = time.monotonic,
) -> Backend:
    """Open ``sim``, ``serial`` or ``can`` (ValueError for another name)."""
    if name == "sim":
        link, fw = importlib.import_module(SIM_BACKEND).open_sim(cfg, control, ticks_per_rev)
        return Backend(name, link, fw)
    return Backend(name, open_link(name, cfg.link, clock))
