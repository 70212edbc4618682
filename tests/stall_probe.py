"""The host's own scheduling stalls, for tests whose bounds depend on the host (HIL).

No third-party imports: the HIL subscriber process runs one too."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable, Sequence


class StallProbe:
    """The host's own scheduling stalls, measured independently of the code under test:
    a thread asks to wake every ``period`` s and records each wake-up later than
    ``threshold`` s as a stall ``(start, end)`` on ``time.monotonic`` (the clock every
    process shares).  A preempted VM or a starved CPU shows here as it does in the
    daemon; a slow daemon does not."""

    def __init__(self, period: float = 0.002, threshold: float = 0.02) -> None:
        self.period, self.threshold = period, threshold
        self.stalls: list[tuple[float, float]] = []
        self.worst = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stall-probe", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            t0 = time.monotonic()
            time.sleep(self.period)
            t1 = time.monotonic()
            late = t1 - t0 - self.period
            self.worst = max(self.worst, late)
            if late > self.threshold:
                self.stalls.append((t0 + self.period, t1))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


def stalled(stalls: Iterable[tuple[float, float]], t0: float, t1: float) -> float:
    """Seconds inside [t0, t1] covered by at least one stall (overlaps counted once)."""
    total, end = 0.0, t0
    for a, b in sorted(stalls):
        a, b = max(a, end), min(b, t1)
        if b > a:
            total += b - a
            end = b
    return total


def near(stalls: Iterable[tuple[float, float]], t: float, before: float, after: float) -> bool:
    """Whether ``t`` lies within ``before`` s ahead of a stall to ``after`` s past it."""
    return any(a - before <= t <= b + after for a, b in stalls)


def daemon_stalls(
    t: Sequence[float],
    lateness_us: Sequence[float],
    compute_us: Sequence[float],
    cpu_us: Sequence[float],
    threshold: float = 0.01,
) -> list[tuple[float, float]]:
    """The host's stalls as the daemon's own log shows them (its time base, s): a wake-up
    later than ``threshold`` s, or a cycle that waited (wall compute minus the loop
    thread's CPU time) longer than ``threshold`` s.  The ``compute_us``/``cpu_us`` of row
    k are the previous cycle's."""
    out: list[tuple[float, float]] = []
    for k in range(len(t)):
        late = lateness_us[k] * 1e-6
        if late > threshold:
            out.append((t[k] - late, t[k]))
        if k > 0 and (compute_us[k] - cpu_us[k]) * 1e-6 > threshold:
            out.append((t[k - 1], t[k]))
    return out


def excused(
    t: Sequence[float],
    active: Sequence[bool],
    stalls: Sequence[tuple[float, float]],
    recovery: float,
    lead: float = 0.05,
) -> list[bool]:
    """Which non-ACTIVE samples the host's stalls explain.  A non-ACTIVE episode that
    starts within ``lead`` s before a stall to 0.2 s after one is excused up to the last
    such stall's end plus ``recovery`` s (the supervisor's recovery time and a margin);
    samples of the episode beyond that, and episodes no stall explains, are not."""
    out = [False] * len(t)
    k = 0
    while k < len(t):
        if active[k]:
            k += 1
            continue
        j = k
        while j < len(t) and not active[j]:
            j += 1
        ends = [b for a, b in stalls if a - lead <= t[k] <= b + 0.2 or t[k] <= a <= t[j - 1]]
        if ends:
            until = max(ends) + recovery
            for m in range(k, j):
                out[m] = t[m] <= until
        k = j
    return out
