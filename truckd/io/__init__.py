"""Transports to the microcontroller: one :class:`~truckd.io.link.Link` interface,
backends by name, imported lazily (the simulator needs no hardware library).

- ``can``: python-can (:class:`truckd.io.can_link.CanLink`)
- ``serial``: pyserial with COBS/CRC-16 framing (:class:`truckd.io.serial_link.SerialLink`)
- ``inproc``: an in-process pair for simulated time (:func:`truckd.io.inproc.inproc_pair`)

Typed messages with counters and receive checks sit on top: :mod:`truckd.io.port`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from truckd.io.config import LinkConfig
from truckd.io.link import Link, LinkDownError, LinkStats

BACKENDS = ("can", "serial")
"""Backends :func:`open_link` opens by name (``inproc`` comes as a pair, see above)."""

__all__ = ["BACKENDS", "Link", "LinkConfig", "LinkDownError", "LinkStats", "open_link"]


def open_link(
    backend: str, config: LinkConfig, clock: Callable[[], float] = time.monotonic
) -> Link:
    """Open the named backend with the settings of ``config``.

    The link is returned even when the device is absent (``link.connected`` False); it
    keeps trying to open it.  Raises ValueError for an unknown backend name.
    """
    if backend == "serial":
        from truckd.io.serial_link import SerialLink

        return SerialLink(
            config.serial_device, config.serial_baudrate, config.reconnect_interval, clock
        )
    if backend == "can":
        from truckd.io.can_link import CanLink

        return CanLink(
            config.can_interface,
            config.can_channel,
            config.can_bitrate,
            config.reconnect_interval,
            clock,
        )
    raise ValueError(f"unknown link backend {backend!r}; expected one of {BACKENDS}")
