"""One sender's plans as the loop takes them: a sample kept on Zenoh's thread with
constant work, decoded by the loop at most once a cycle, checked, the newest kept
(:class:`PlanReceiver`); and the key a vehicle's plan is published on."""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from typing import Protocol

from truckd.control.platoon import Plan, decode_plan


def plan_key(vehicle_id: str) -> str:
    """The Zenoh key of a vehicle's plan (reference section 5)."""
    return f"truckd/{vehicle_id}/plan"


MAX_PLAN_BYTES = 65536
"""A plan payload longer than this is refused undecoded (a 40-step plan is about 2 kB)."""


class _Payload(Protocol):
    def to_bytes(self) -> bytes: ...


class PlanReceiver:
    """The newest valid plan from one predecessor, insulated from the sender's rate.

    :meth:`on_payload` runs on Zenoh's thread for every sample and does constant work:
    it counts the sample and keeps it as the pending one (a ring of one: a pending sample
    not yet decoded is replaced and counted in ``dropped``).  :meth:`latest`, called by
    the loop once per cycle, decodes the pending sample (at most one per call, so at most
    one decode per cycle and key whatever the sender's rate) and returns the newest valid
    plan.  Refused and counted: payloads longer than :data:`MAX_PLAN_BYTES` or that do
    not parse, plans naming another sender, plans stamped more than ``max_skew_s`` in the
    future of ``clock`` (when given: one such plan held would lock out every genuine one
    after it), plans older (by ``seq``) than the one held unless the sender restarted (its
    clock moved on by more than a second).  Thread-safe."""

    def __init__(
        self,
        predecessor: str,
        clock: Callable[[], float] | None = None,
        max_skew_s: float = math.inf,
    ) -> None:
        self.predecessor = predecessor
        self.clock = clock
        self.max_skew_s = max_skew_s
        self.key = plan_key(predecessor)
        self._lock = threading.Lock()
        self._latest: Plan | None = None
        self._pending: bytes | _Payload | None = None
        self.received = 0
        """Samples that arrived on the key (every one, also those dropped)."""
        self.decoded = 0
        """Samples decoded (at most one per :meth:`latest` call)."""
        self.accepted = 0
        self.refused = 0
        self.last_error = ""
        self.blocked = False
        """Injected link loss (HIL runs): every plan is dropped while set."""
        self.dropped = 0
        """Samples never decoded: replaced by a newer one before the loop took it, or
        received while the link was blocked."""

    def on_payload(self, payload: bytes | _Payload) -> None:
        """One sample arrived (Zenoh's thread): constant work, no decoding."""
        with self._lock:
            self.received += 1
            if self.blocked:
                self.dropped += 1
                return
            if self._pending is not None:
                self.dropped += 1
            self._pending = payload

    def _take(self, max_bytes: int = MAX_PLAN_BYTES) -> None:
        with self._lock:
            raw, self._pending = self._pending, None
        if raw is None:
            return
        self.decoded += 1
        try:
            data = raw if isinstance(raw, bytes) else raw.to_bytes()
            if len(data) > max_bytes:
                raise ValueError(f"{len(data)} bytes, more than {max_bytes}")
            plan = decode_plan(data)
        except Exception as exc:  # any payload at all: nested too deep, not UTF-8, ...
            self.refused += 1
            self.last_error = str(exc)[:200] or type(exc).__name__
            return
        if plan.vehicle_id and plan.vehicle_id != self.predecessor:
            self.refused += 1
            self.last_error = f"plan from {plan.vehicle_id!r}, expected {self.predecessor!r}"
            return
        ahead = plan.t - self.clock() if self.clock is not None else -math.inf
        if ahead > self.max_skew_s:
            self.refused += 1
            self.last_error = f"plan stamped {ahead:.3f} s in the future"
            return
        with self._lock:
            old = self._latest
            if old is None or plan.seq > old.seq or plan.t > old.t + 1.0:
                self._latest = plan
                self.accepted += 1
                return
        self.refused += 1
        self.last_error = f"plan seq {plan.seq} not newer than the one held ({old.seq})"

    def latest(self, max_bytes: int = MAX_PLAN_BYTES) -> Plan | None:
        """Decode the pending sample, if any (one at most; refused when longer than
        ``max_bytes``), and return the newest valid plan (the loop's side: call it once
        per cycle)."""
        self._take(max_bytes)
        with self._lock:
            return self._latest
