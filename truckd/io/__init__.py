"""Transports to the microcontroller: one :class:`~truckd.io.link.Link` interface and
its implementations, each in its own module so a hardware library is imported only by
the backend that uses it (the registry of backends by name: :mod:`truckd.io.backends`).

- ``can``: python-can (:class:`truckd.io.can_link.CanLink`)
- ``serial``: pyserial with COBS/CRC-16 framing (:class:`truckd.io.serial_link.SerialLink`)
- ``inproc``: an in-process pair for simulated time (:func:`truckd.io.inproc.inproc_pair`)

Typed messages with counters and receive checks sit on top: :mod:`truckd.io.port`.
"""

from __future__ import annotations

from truckd.io.config import LinkConfig
from truckd.io.link import Link, LinkDownError, LinkStats

__all__ = ["Link", "LinkConfig", "LinkDownError", "LinkStats"]
