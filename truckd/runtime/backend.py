"""The daemon's link to the microcontroller, by backend name.

``serial`` and ``can`` open the real transports (truckd.io, settings in ``link:``);
``sim`` puts the simulated firmware and plant on an in-process link and advances them
by one control period per cycle, in real time (the lead drives the ``follow`` scenario).

One daemon per device: :func:`claim_backend` locks the device (:mod:`truckd.io.devlock`)
before anything opens it, and :func:`open_backend` fails (DeviceBusyError) rather than
retry when the first open finds the device held by another process.  A device that is
simply absent is not an error: the link names it in the log and keeps retrying.
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
from truckd.io.config import LinkConfig
from truckd.io.devlock import (
    DeviceBusyError,
    DeviceLock,
    can_keys,
    claim_device,
    pids_holding,
    serial_keys,
)
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
    lock: DeviceLock | None = None

    def tick(self, dt: float) -> None:
        """Advance the simulated truck by ``dt`` s (no-op on real hardware)."""
        if self.firmware is not None:
            self.firmware.step(dt)

    def close(self) -> None:
        """Close the link, then release the device lock."""
        self.link.close()
        if self.lock is not None:
            self.lock.release()


def device_name(name: str, link: LinkConfig) -> str:
    """What error messages call the device of backend ``name``."""
    if name == "serial":
        return f"serial device {link.serial_device}"
    if name == "can":
        return f"CAN interface {link.can_interface} channel {link.can_channel}"
    return f"backend {name}"


def claim_backend(name: str, link: LinkConfig) -> DeviceLock:
    """Lock the device of ``serial``/``can`` (nothing opened, nothing sent); ``sim`` has
    nothing to lock.  DeviceBusyError names the device and the pid holding it."""
    if name == "serial":
        keys = serial_keys(link.serial_device)
    elif name == "can":
        keys = can_keys(link.can_interface, link.can_channel)
    else:
        keys = []
    return claim_device(device_name(name, link), keys)


def open_backend(
    name: str,
    cfg: TruckConfig,
    control: ControlConfig,
    ticks_per_rev: int,
    clock: Callable[[], float] = time.monotonic,
    lock: DeviceLock | None = None,
) -> Backend:
    """Open ``sim``, ``serial`` or ``can`` (ValueError for another name).

    ``lock`` (from :func:`claim_backend`) is released by :meth:`Backend.close`.  When the
    first open finds the device held by another process the link is closed again without
    a byte sent and DeviceBusyError is raised (``lock`` stays with the caller)."""
    if name == "sim":
        link, fw = importlib.import_module(SIM_BACKEND).open_sim(cfg, control, ticks_per_rev)
        return Backend(name, link, fw)
    link = open_link(name, cfg.link, clock)
    if link.busy:
        link.close()
        what = device_name(name, cfg.link)
        pids = pids_holding(cfg.link.serial_device) if name == "serial" else []
        by = f"process {', '.join(map(str, pids))}" if pids else "another process"
        raise DeviceBusyError(f"{what} is in use by {by}; one daemon per device")
    return Backend(name, link, lock=lock)
