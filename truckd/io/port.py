"""Typed messages over a link: counters on send, receive checks on receive.

The companion computer (the daemon, the simulation) uses :func:`companion_port`; the
simulated firmware uses :func:`firmware_port`.  ``clock`` (s) stamps received messages
and judges freshness: pass the simulated time in simulation, ``time.monotonic`` on the
car.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from firmware_protocol.checks import COUNTER_MODULO, RESYNC, RxChecker
from firmware_protocol.codec import encode, message_name
from firmware_protocol.messages import Message
from truckd.io.link import Link

COMPANION_RX = ("WHEEL_ENCODERS", "MOTOR_FEEDBACK", "RANGE", "FIRMWARE_HEARTBEAT")
"""Messages the companion computer receives."""

FIRMWARE_RX = ("MOTOR_CMD", "COMPANION_HEARTBEAT")
"""Messages the microcontroller receives."""


@dataclass(frozen=True, slots=True)
class Received:
    """A message that passed every receive check, stamped with ``clock()`` (s)."""

    t: float
    name: str
    msg: Message


class Port:
    """Send typed messages with per-message counters; receive only checked messages."""

    def __init__(
        self,
        link: Link,
        expect: Iterable[str],
        clock: Callable[[], float] = time.monotonic,
        timeout_periods: float = 5.0,
        resync: int = 0,
    ) -> None:
        self.link = link
        self.clock = clock
        self.checker = RxChecker(
            expect=tuple(expect), timeout_periods=timeout_periods, resync=resync
        )
        self._counters: dict[str, int] = {}

    def send(self, msg: Message) -> bool:
        """Encode and send (COUNTER advances per message); False if not sent.

        Raises ValueError for a non-finite value (nothing is sent).
        """
        name = message_name(msg)
        c = self._counters.get(name, 0)
        frame = encode(msg, c)
        self._counters[name] = (c + 1) % COUNTER_MODULO
        return self.link.send(frame)

    def recv(self, timeout: float = 0.0) -> Received | None:
        """The next message that passes the checks, waiting up to ``timeout`` s."""
        deadline = time.monotonic() + timeout
        wait = timeout
        while True:
            frame = self.link.recv(wait)
            if frame is None:
                return None
            now = self.clock()
            dec = self.checker.accept(frame, now)
            if dec is not None:
                return Received(now, dec.name, dec.msg)
            wait = max(0.0, deadline - time.monotonic()) if timeout > 0 else 0.0

    def poll(self) -> list[Received]:
        """Every checked message available now (non-blocking)."""
        frames = self.link.recv_all()
        if not frames:
            return []
        now = self.clock()  # all read at once: one stamp
        accept = self.checker.accept
        out: list[Received] = []
        for frame in frames:
            dec = accept(frame, now)
            if dec is not None:
                out.append(Received(now, dec.name, dec.msg))
        return out

    def fresh(self, name: str) -> bool:
        """True when ``name`` arrived within its freshness timeout."""
        return self.checker.fresh(name, self.clock())

    def freshness(self) -> dict[str, bool]:
        """Freshness of every expected message."""
        return self.checker.freshness(self.clock())

    def stats(self) -> dict[str, int | bool]:
        """Link and receive-check counters, flat, JSON-ready (plus ``connected``)."""
        self.checker.poll_timeouts(self.clock())
        d: dict[str, int | bool] = {"connected": self.link.connected}
        d.update(self.link.stats.as_dict())
        d.update({f"rx_{k}": v for k, v in self.checker.stats.as_dict().items()})
        return d


def companion_port(
    link: Link, clock: Callable[[], float] = time.monotonic, timeout_periods: float = 5.0
) -> Port:
    """The companion computer's end: receives sensor messages and the MCU heartbeat."""
    return Port(link, COMPANION_RX, clock, timeout_periods)


def firmware_port(
    link: Link, clock: Callable[[], float] = time.monotonic, timeout_periods: float = 5.0
) -> Port:
    """The microcontroller's end: receives motor commands and the companion heartbeat
    (a replayed loop of commands is rejected: ``RESYNC``, see :mod:`firmware_protocol.checks`)."""
    return Port(link, FIRMWARE_RX, clock, timeout_periods, resync=RESYNC)
