"""The plans a follower hears from every truck (``platoon.order: auto``): a receiver per
sender on ``truckd/*/plan``, the discovery view of who follows whom
(:class:`~truckd.runtime.platoon_follow.HeardPlans`), and bounded work per cycle: the
predecessor's and the standby's plans each cycle, another sender's now and then, at most
:data:`MAX_SENDERS` senders, silent ones forgotten."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

from truckd.control.platoon import Plan
from truckd.runtime.plan_receiver import PlanReceiver, _Payload
from truckd.runtime.platoon_follow import Follow, HeardPlans

HEAR_OTHERS_EVERY = 10
"""``platoon.order: auto`` while following: another sender's plan is decoded once every
this many cycles, in turn (a decode costs about 30 us; the chain changes when a truck
announces a join, long before it moves in): with 10 trucks each is heard every second."""

MAX_SENDERS = 32
"""``platoon.order: auto``: plans are heard from at most this many trucks (the first
heard, and always the configured predecessor, the one followed and the standby); samples
from more are dropped and counted (``senders_refused`` in health); a sender silent for
:data:`SILENT_S` is forgotten, making room."""

SILENT_S = 4.0
"""s: a sender heard from no sample this long is forgotten (its receiver and what its
plans said of the order), unless configured or followed: five ``plan_hold_s``."""

OTHER_PLAN_BYTES = 16384
"""Plans of senders neither followed nor the standby are decoded up to this size only (a
plan of 40 steps is about 2 kB, of the configuration's longest horizon about 20 kB: such
a truck is heard once it is the standby, as its follower's predecessor, not as a joiner
or a tail); a decode of 64 kB costs about 2.4 ms."""

SEARCH_DECODES = 4
"""Senders decoded per cycle, in turn, while no predecessor is followed (the tail search)
or the plans have been heard for less than ``cacc_return_s``."""


def plan_sender(key: str) -> str | None:
    """The vehicle id of a plan key ``truckd/<id>/plan``; None for any other key."""
    parts = key.split("/")
    if len(parts) == 3 and parts[0] == "truckd" and parts[2] == "plan" and parts[1]:
        return parts[1]
    return None


class PlanHearing:
    """Every sender's receiver and what their plans say of the order (see the module
    docstring).  :meth:`on_sample` runs on Zenoh's thread; the rest on the loop's."""

    def __init__(
        self,
        vehicle_id: str,
        configured: str,
        skew_clock: Callable[[], float] | None,
        max_skew_s: float,
    ) -> None:
        """``configured``: the configured predecessor (always heard, never forgotten);
        ``skew_clock`` and ``max_skew_s``: each receiver's future-stamp check
        (:class:`PlanReceiver`)."""
        self.vehicle_id = vehicle_id
        self.configured = configured
        self._skew_clock, self._max_skew_s = skew_clock, max_skew_s
        self.receivers: dict[str, PlanReceiver] = {}
        """Vehicle id -> receiver (replaced whole under the lock, never changed in place:
        readers on either thread see the old or the new)."""
        self._lock = threading.Lock()
        self.blocked = False
        self.senders_refused = 0
        """Samples from senders beyond :data:`MAX_SENDERS` (dropped)."""
        self.heard = HeardPlans()
        self._turn = 0
        self._wanted: frozenset[str] = frozenset({configured} - {""})
        """Senders always admitted: the configured predecessor, the one followed, the
        standby (written by the loop, read by Zenoh's thread: one reference swapped)."""
        self._activity: dict[str, tuple[int, float]] = {}
        """Per sender: samples received and when that count last changed (monotonic s)."""
        self.first_heard = math.nan
        """When the first plan of another truck was heard (monotonic s, NaN: none yet)."""

    @property
    def received(self) -> int:
        """Samples received from every sender heard now."""
        return sum(r.received for r in self.receivers.values())

    def on_sample(self, key: str, payload: bytes | _Payload) -> None:
        """A plan sample on ``key`` (Zenoh's thread): handed to its sender's receiver
        (made at the sender's first sample); constant work, no decoding."""
        sender = plan_sender(key)
        if sender is None or sender == self.vehicle_id:
            return
        r = self.receivers.get(sender)
        if r is None:
            with self._lock:
                r = self.receivers.get(sender)
                if r is None:
                    if len(self.receivers) >= MAX_SENDERS and sender not in self._wanted:
                        self.senders_refused += 1
                        return
                    r = PlanReceiver(sender, self._skew_clock, self._max_skew_s)
                    r.blocked = self.blocked
                    self.receivers = {**self.receivers, sender: r}
        r.on_payload(payload)

    def block(self, blocked: bool) -> None:
        """Drop every plan received while ``blocked`` (an injected link loss)."""
        with self._lock:
            self.blocked = blocked
            for r in self.receivers.values():
                r.blocked = blocked

    def hear(self, f: Follow, now: float, mono: float, settled: bool) -> None:
        """One cycle's hearing for the follower ``f``: the newest plans of its predecessor
        and its standby into their sources (clocks estimated apart; ``now`` on this
        truck's clock, s) and noted in :attr:`heard` (at ``mono``, the order's monotonic
        clock); one other sender in turn every :data:`HEAR_OTHERS_EVERY` cycles, or
        :data:`SEARCH_DECODES` a cycle while ``f`` follows nobody or the plans are not
        yet ``settled``; senders silent for :data:`SILENT_S` forgotten."""
        receivers = self.receivers
        if receivers and math.isnan(self.first_heard):
            self.first_heard = mono
        mine = (f.source.sender, f.standby.sender)
        self._wanted = frozenset({self.configured, *mine} - {""})
        for src in (f.source, f.standby):
            r = receivers.get(src.sender) if src.sender else None
            plan = r.latest() if r is not None else None
            if plan is not None:
                src.hold_latest(plan, now)
                self.heard.note(src.sender, plan, mono)
        self._turn += 1
        k, turn = divmod(self._turn, HEAR_OTHERS_EVERY)
        if not turn:
            self._forget_silent(mono, {self.configured, f.predecessor})
            receivers = self.receivers
        others = [v for v in receivers if v not in mine]
        if others and f.predecessor and settled:  # one every HEAR_OTHERS_EVERY cycles
            others = [] if turn else [others[k % len(others)]]
        elif len(others) > SEARCH_DECODES:  # searching or settling: every sender soon
            k = self._turn * SEARCH_DECODES
            others = [others[(k + i) % len(others)] for i in range(SEARCH_DECODES)]
        for vid in others:
            other: Plan | None = receivers[vid].latest(OTHER_PLAN_BYTES)
            if other is not None:
                self.heard.note(vid, other, mono)

    def _forget_silent(self, mono: float, kept: set[str]) -> None:
        """Senders with no sample for :data:`SILENT_S` are forgotten, but for ``kept`` (the
        configured predecessor and the one followed; a silent standby is forgotten: an
        announced joiner that fell silent no longer holds the room open)."""
        gone = []
        for vid, r in self.receivers.items():
            count, since = self._activity.get(vid, (-1, mono))
            if r.received != count:
                self._activity[vid] = (r.received, mono)
            elif mono - since >= SILENT_S and vid not in kept:
                gone.append(vid)
        if gone:
            with self._lock:
                self.receivers = {v: r for v, r in self.receivers.items() if v not in gone}
            for vid in gone:
                self._activity.pop(vid, None)
                self.heard.forget(vid)
