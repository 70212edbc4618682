"""A predecessor's clock seen from the receiver's: offset and drift from one-way stamps.

Pure numerics: no I/O, no clock.  Every plan carries the sender's time ``t`` on the
sender's clock; the receiver notes its own time when the plan arrives.  With the sender's
clock ``s`` and the receiver's ``r`` related by ``r = s + o + d (s - s_ref)`` (offset ``o``
in seconds, drift ``d``: 1e-4 is 100 ppm) and a transport delay ``delay >= 0``, each
message gives ``y = r_arrival - s_sent = o + d (s - s_ref) + delay``.  Delays are never
negative, so the lower envelope of ``y`` over the sender's time is the clock line plus the
smallest delay: :class:`ClockEstimator` keeps the smallest ``y`` of each bucket of
``bucket_s`` (sender's time), fits the drift as the slope through those minima (least
squares, at least three buckets), and puts the line under the lowest of them.

What one-way stamps cannot give: the smallest transport delay is counted in the offset
(a plan then looks younger by it; with a link's delay drawn from 0-50 ms and 100 messages
a second, a bucket's smallest delay is about half a millisecond).  A sample more than
``step_s`` below the line (a message cannot arrive before it was sent), or ``step_s``
above it ``step_count`` times in a row, is a clock step (a restarted or re-synchronised
sender or receiver): the estimate restarts from that sample.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True)
class ClockEstimate:
    """``own = sent + offset + drift (sent - ref)`` (s): the receiver's time of a sender's
    time ``sent``, the smallest transport delay included in ``offset``."""

    offset: float
    drift: float
    ref: float

    def to_own(self, sent: float) -> float:
        """The receiver's time (s) of the sender's time ``sent`` (s)."""
        return sent + self.offset + self.drift * (sent - self.ref)


class ClockEstimator:
    """Offset and drift of one sender's clock against the receiver's (module docstring).

    ``observe(sent, arrived)`` per message (any order: reordered messages are fine);
    :attr:`estimate` is None until the first message.  ``max_drift`` bounds the fitted
    slope (crystal clocks drift by tens of ppm; a larger slope is the delay's noise)."""

    def __init__(
        self,
        bucket_s: float = 1.0,
        buckets: int = 60,
        step_s: float = 0.5,
        step_count: int = 10,
        max_drift: float = 1e-3,
    ) -> None:
        if not (bucket_s > 0.0 and buckets >= 3 and step_s > 0.0 and step_count >= 1):
            raise ValueError("bucket_s and step_s must be positive, buckets at least 3")
        self.bucket_s = bucket_s
        self.buckets = buckets
        self.step_s = step_s
        self.step_count = step_count
        self.max_drift = max_drift
        self._min: deque[tuple[int, float, float]] = deque()
        """Per bucket (sender's time): (index, sent, y) of its smallest ``y``."""
        self._above = 0
        self.estimate: ClockEstimate | None = None
        self.steps = 0
        """Clock steps seen (restarts of the estimate)."""

    def reset(self) -> None:
        """Forget everything (the sender changed)."""
        self._min.clear()
        self._above = 0
        self.estimate = None

    def observe(self, sent: float, arrived: float) -> None:
        """A message stamped ``sent`` (sender's clock, s) arrived at ``arrived`` (the
        receiver's clock, s)."""
        if not (math.isfinite(sent) and math.isfinite(arrived)):
            return
        y = arrived - sent
        est = self.estimate
        if est is not None:
            dev = y - (est.to_own(sent) - sent)
            if dev < -self.step_s:
                self.steps += 1
                self.reset()
            elif dev > self.step_s:
                self._above += 1
                if self._above < self.step_count:
                    return  # one very late message, or the first of a step: wait
                self.steps += 1
                self.reset()
            else:
                self._above = 0
        idx = math.floor(sent / self.bucket_s)
        q = self._min
        if q and idx < q[0][0]:
            return  # older than the window
        for j in range(len(q) - 1, -1, -1):
            if q[j][0] == idx:
                if y < q[j][2]:
                    q[j] = (idx, sent, y)
                    self._fit()
                return
            if q[j][0] < idx:
                q.insert(j + 1, (idx, sent, y))
                break
        else:
            q.appendleft((idx, sent, y))
        while q[-1][0] - q[0][0] >= self.buckets:
            q.popleft()
        self._fit()

    def _fit(self) -> None:
        q = self._min
        ref = q[-1][1]
        drift = 0.0
        if len(q) >= 3:
            n = len(q)
            ms = sum(s for _, s, _ in q) / n
            my = sum(y for _, _, y in q) / n
            sxx = sum((s - ms) ** 2 for _, s, _ in q)
            if sxx > 0.0:
                sxy = sum((s - ms) * (y - my) for _, s, y in q)
                drift = min(max(sxy / sxx, -self.max_drift), self.max_drift)
        offset = min(y - drift * (s - ref) for _, s, y in q)
        self.estimate = ClockEstimate(offset, drift, ref)

    def to_own(self, sent: float) -> float:
        """The receiver's time (s) of the sender's time ``sent``; NaN before any message."""
        est = self.estimate
        return est.to_own(sent) if est is not None else math.nan
