"""An operator's order to a running truck with ``platoon.order: auto``: join behind a
truck, or drive alone.

``truckd/<vehicle id>/platoon_join`` carries ``{"behind": "<vehicle id>"}`` (drive behind
that truck: announced in this truck's plans, so the truck behind it opens room; the
merge itself is the driver's or the lane change's) or ``{"behind": null}`` (follow
nobody, ACC on the range sensor, no tail searched until told to join again).  With
fleet TLS only an operator's certificate may put it (:mod:`.fleet_tls`).  Messages
arrive on Zenoh's thread; the control loop takes the newest once a cycle
(:meth:`JoinOrders.take`), between the estimate and the control law.  Anything else is
refused, counted and logged, and changes nothing.
"""

from __future__ import annotations

import json
import logging
from collections import deque

from truckd.config.ids import VEHICLE_ID_EXPECTED, VEHICLE_ID_RE

log = logging.getLogger(__name__)

MAX_JOIN_BYTES = 256
"""Largest order accepted (bytes): ``{"behind": "<64 characters>"}`` is about 80."""

ALONE = None
"""``behind`` of an order to drive alone."""


def join_key(vehicle_id: str) -> str:
    """The Zenoh key a truck takes join orders on."""
    return f"truckd/{vehicle_id}/platoon_join"


def parse_join(payload: bytes, own_id: str) -> str | None:
    """The truck to drive behind (None: alone) of an order; ValueError with the reason
    for anything else (not JSON, another key, an id that is no vehicle id, this truck)."""
    if len(payload) > MAX_JOIN_BYTES:
        raise ValueError(f"{len(payload)} bytes, more than {MAX_JOIN_BYTES}")
    try:
        order = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        raise ValueError("not JSON") from None
    if not isinstance(order, dict) or set(order) != {"behind"}:
        raise ValueError('expected {"behind": "<vehicle id>"} or {"behind": null}')
    behind = order["behind"]
    if behind is None:
        return ALONE
    if not isinstance(behind, str) or not VEHICLE_ID_RE.fullmatch(behind):
        raise ValueError(f"behind: {str(behind)[:80]!r}: expected {VEHICLE_ID_EXPECTED}")
    if behind == own_id:
        raise ValueError(f"behind: {behind!r} is this truck")
    return behind


class JoinOrders:
    """The join orders a truck received: the newest waiting for the loop, and counts."""

    def __init__(self, own_id: str) -> None:
        self.own_id = own_id
        self._waiting: deque[str | None] = deque(maxlen=1)
        self.told = 0
        """Orders taken by the loop."""
        self.refused = 0
        """Orders refused (see :func:`parse_join`)."""
        self.last = ""
        """The last order taken or refused, in words."""

    def on_payload(self, payload: bytes) -> None:
        """A message on :func:`join_key` (Zenoh's thread): kept when valid (the newest
        replaces one not yet taken), else counted and logged."""
        try:
            behind = parse_join(bytes(payload), self.own_id)
        except ValueError as exc:
            self.refused += 1
            self.last = f"refused: {exc}"
            log.warning("platoon join order refused: %s", exc)
            return
        self._waiting.append(behind)

    def take(self) -> tuple[bool, str | None]:
        """``(True, behind)`` for the newest order not taken yet, else ``(False, None)``
        (the control loop, once a cycle)."""
        try:
            behind = self._waiting.popleft()
        except IndexError:
            return False, None
        self.told += 1
        self.last = "drive alone" if behind is None else f"join behind {behind}"
        log.info("platoon: told to %s", self.last)
        return True, behind
