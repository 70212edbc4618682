"""A plan link in simulated time: delay drawn per message, random or bursty loss, loss
windows (``truckd sim --platoon``)."""

from __future__ import annotations

import heapq
import random
from dataclasses import dataclass

from truckd.control.platoon import Plan


@dataclass(frozen=True)
class LinkConfig:
    """A plan link as it is: each message's delay drawn uniformly in ``delay`` (lo, hi) s
    (so it changes during the run, and messages overtake each other when the range is
    wider than the sending period), lost with probability ``loss``; with ``burst`` the
    losses come in runs (a two-state Gilbert-Elliott channel: the same share lost, runs of
    ``burst_len`` messages on average)."""

    delay: tuple[float, float] = (0.02, 0.02)
    loss: float = 0.0
    burst: bool = False
    burst_len: float = 8.0


class PlanChannel:
    """One sender's plan key as one receiver gets it (:class:`LinkConfig`, plus the
    scenario's loss windows ``(t0, t1, p)``): :meth:`receive` gives the plans delivered
    by a time with their delivery times, in delivery order."""

    def __init__(
        self,
        link: LinkConfig,
        windows: tuple[tuple[float, float, float], ...],
        rng: random.Random,
        name: str = "",
    ) -> None:
        self.name = name
        """``sender->receiver``."""
        self.link = link
        self.windows = windows
        self.rng = rng
        self._inflight: list[tuple[float, int, Plan]] = []
        self._bad = False
        self.sent = 0
        self.lost = 0

    def _lost(self, t: float) -> bool:
        link, rng = self.link, self.rng
        for t0, t1, pw in self.windows:
            if t0 <= t < t1 and rng.random() < pw:
                return True
        p = link.loss
        if not link.burst or p <= 0.0 or p >= 1.0:
            return rng.random() < p
        leave_bad = 1.0 / link.burst_len
        enter_bad = p * leave_bad / (1.0 - p)  # stationary share of the bad state: p
        self._bad = rng.random() >= leave_bad if self._bad else rng.random() < enter_bad
        return self._bad

    def send(self, t: float, plan: Plan) -> None:
        """Publish at time t (s, simulated)."""
        self.sent += 1
        if self._lost(t):
            self.lost += 1
            return
        lo, hi = self.link.delay
        delay = lo if hi <= lo else self.rng.uniform(lo, hi)
        heapq.heappush(self._inflight, (t + delay, self.sent, plan))

    def receive(self, t: float) -> list[tuple[float, Plan]]:
        """The plans delivered by time t (s), with their delivery times."""
        q, out = self._inflight, []
        while q and q[0][0] <= t + 1e-12:
            at, _, plan = heapq.heappop(q)
            out.append((at, plan))
        return out
