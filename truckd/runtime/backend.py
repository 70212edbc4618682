"""The daemon's link to the microcontroller, by backend name.

One registry (:data:`truckd.io.backends.BACKENDS`) names every backend with the module
and class implementing it, imported only when the name is asked for (as python-can loads
its interfaces): ``serial`` and ``can`` open the real transports (truckd.io, settings in
``link:``, classes here); ``sim`` (:class:`truckd.sim.backend.SimBackend`) puts the
simulated truck on an in-process link and advances it by one control period per cycle.
So this package never imports :mod:`truckd.sim`: ``truckd run`` on the car never loads
the plant or the scenarios.

One daemon per device: :func:`claim_backend` locks the device (:mod:`truckd.io.devlock`)
before anything opens it, and :func:`open_backend` fails (DeviceBusyError) rather than
retry when the first open finds the device held by another process.  A device that is
simply absent is not an error: the link names it in the log and keeps retrying.
"""

from __future__ import annotations

import importlib
import time
from collections.abc import Callable

from truckd.config.truck import TruckConfig
from truckd.control.config import ControlConfig
from truckd.io.backends import BACKEND_NAMES, BACKENDS
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

Clock = Callable[[], float]


class Backend:
    """A link to the firmware plus what it needs each cycle; one subclass per name in
    :data:`~truckd.io.backends.BACKENDS`."""

    name = ""

    def __init__(self, link: Link, lock: DeviceLock | None = None) -> None:
        self.link = link
        self.lock = lock

    @classmethod
    def device(cls, link: LinkConfig) -> tuple[str, list[str]]:
        """What error messages call the device, and the keys that lock it (none: nothing
        to lock)."""
        return f"backend {cls.name}", []

    @classmethod
    def open(
        cls,
        cfg: TruckConfig,
        control: ControlConfig,
        clock: Clock,
        lock: DeviceLock | None,
    ) -> Backend:
        """Open the backend (the device may be absent: the link keeps retrying)."""
        raise NotImplementedError

    def tick(self, dt: float) -> None:
        """Advance what the backend simulates by ``dt`` s (real hardware: nothing)."""

    def close(self) -> None:
        """Close the link, then release the device lock."""
        self.link.close()
        if self.lock is not None:
            self.lock.release()


class SerialBackend(Backend):
    """pyserial, COBS/CRC-16 framing (:class:`truckd.io.serial_link.SerialLink`)."""

    name = "serial"

    @classmethod
    def device(cls, link: LinkConfig) -> tuple[str, list[str]]:
        return f"serial device {link.serial_device}", serial_keys(link.serial_device)

    @classmethod
    def open(
        cls,
        cfg: TruckConfig,
        control: ControlConfig,
        clock: Clock,
        lock: DeviceLock | None,
    ) -> Backend:
        from truckd.io.serial_link import SerialLink

        c = cfg.link
        link = SerialLink(c.serial_device, c.serial_baudrate, c.reconnect_interval, clock)
        return cls(_not_busy(link, cls.device(c)[0], pids_holding(c.serial_device)), lock)


class CanBackend(Backend):
    """python-can, any interface (:class:`truckd.io.can_link.CanLink`)."""

    name = "can"

    @classmethod
    def device(cls, link: LinkConfig) -> tuple[str, list[str]]:
        what = f"CAN interface {link.can_interface} channel {link.can_channel}"
        return what, can_keys(link.can_interface, link.can_channel)

    @classmethod
    def open(
        cls,
        cfg: TruckConfig,
        control: ControlConfig,
        clock: Clock,
        lock: DeviceLock | None,
    ) -> Backend:
        from truckd.io.can_link import CanLink

        c = cfg.link
        link = CanLink(c.can_interface, c.can_channel, c.can_bitrate, c.reconnect_interval, clock)
        return cls(_not_busy(link, cls.device(c)[0], []), lock)


def _not_busy(link: Link, what: str, pids: list[int]) -> Link:
    """``link``, or DeviceBusyError (the link closed again, without a byte sent) when its
    first open found the device held by another process."""
    if link.busy:
        link.close()
        by = f"process {', '.join(map(str, pids))}" if pids else "another process"
        raise DeviceBusyError(f"{what} is in use by {by}; one daemon per device")
    return link


def backend_class(name: str) -> type[Backend]:
    """The class registered for ``name``, its module imported now (ValueError for a name
    the registry does not have)."""
    if name not in BACKENDS:
        raise ValueError(f"unknown backend {name!r}; expected one of {BACKEND_NAMES}")
    module, attr = BACKENDS[name]
    cls = getattr(importlib.import_module(module), attr)
    if not (isinstance(cls, type) and issubclass(cls, Backend)):
        raise TypeError(f"backend {name!r}: {module}.{attr} is not a Backend")
    return cls


def device_name(name: str, link: LinkConfig) -> str:
    """What error messages call the device of backend ``name``."""
    return backend_class(name).device(link)[0]


def claim_backend(name: str, link: LinkConfig) -> DeviceLock:
    """Lock the device of backend ``name`` (nothing opened, nothing sent; a backend with
    no device has nothing to lock).  DeviceBusyError names the device and the pid holding
    it."""
    what, keys = backend_class(name).device(link)
    return claim_device(what, keys)


def open_backend(
    name: str,
    cfg: TruckConfig,
    control: ControlConfig,
    clock: Clock = time.monotonic,
    lock: DeviceLock | None = None,
) -> Backend:
    """Open the backend registered as ``name`` (ValueError for another name).

    ``lock`` (from :func:`claim_backend`) is released by :meth:`Backend.close`.  When the
    first open finds the device held by another process the link is closed again without
    a byte sent and DeviceBusyError is raised (``lock`` stays with the caller)."""
    return backend_class(name).open(cfg, control, clock, lock)
