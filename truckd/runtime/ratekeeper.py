"""A drift-free fixed-rate loop timer with timing statistics.

Deadlines are absolute: period ``k`` ends at ``t0 + k * period`` whatever happened before,
so the rate never drifts.  When a cycle overruns one or more deadlines, the missed periods
are skipped (not made up by running back to back) and counted.

The clock and the sleep are injected (monotonic seconds), so tests drive it with a fake
clock; the daemon passes :func:`time.monotonic` and :func:`time.sleep`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimingStats:
    """Loop timing over a window, microseconds except counts."""

    cycles: int
    misses: int
    skipped_periods: int
    lateness_us_p50: float
    lateness_us_p99: float
    lateness_us_max: float
    compute_us_p50: float
    compute_us_p99: float
    compute_us_max: float

    def as_dict(self) -> dict[str, float | int]:
        """Plain dict for JSON (health telemetry, benchmarks)."""
        return {
            "cycles": self.cycles,
            "misses": self.misses,
            "skipped_periods": self.skipped_periods,
            "lateness_us_p50": self.lateness_us_p50,
            "lateness_us_p99": self.lateness_us_p99,
            "lateness_us_max": self.lateness_us_max,
            "compute_us_p50": self.compute_us_p50,
            "compute_us_p99": self.compute_us_p99,
            "compute_us_max": self.compute_us_max,
        }


class _Ring:
    """Fixed-size ring of float samples (no allocation per cycle)."""

    def __init__(self, size: int) -> None:
        self.buf = np.zeros(size)
        self.n = 0

    def add(self, value: float) -> None:
        self.buf[self.n % self.buf.size] = value
        self.n += 1

    def values(self) -> np.ndarray:
        return self.buf[: min(self.n, self.buf.size)]


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) * 1e6 if values.size else 0.0


class SteppedClock:
    """Simulated time for a loop that drives a simulated truck in process (the ``sim``
    backend): it stands still while a cycle works and advances only when the rate keeper
    sleeps, so the run is the same on a busy machine as on an idle one.  Call it for the
    time (s, from ``t0``); pass :meth:`sleep` as the rate keeper's sleep."""

    def __init__(self, t0: float = 0.0) -> None:
        self.t = t0

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        """Advance by ``seconds`` (s; a negative wait advances nothing)."""
        self.t += max(0.0, seconds)


class RateKeeper:
    """Keeps a loop at ``rate_hz`` on absolute deadlines.

    Use: ``rk.start()`` once, then each cycle ``rk.begin_cycle()`` right after waking (it
    records wake lateness), do the work, then ``rk.keep_time()`` (records compute time,
    detects misses and sleeps until the next deadline).  ``window`` samples are kept for
    the percentile statistics; miss and cycle counters are totals since start.
    """

    def __init__(
        self,
        rate_hz: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
        window: int = 6000,
    ) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be a positive number, got {rate_hz!r}")
        self.period = 1.0 / rate_hz
        self._clock = clock
        self._sleep = sleep
        self._t0 = 0.0
        self._k = 0  # index of the period in progress
        self._wake = 0.0
        self.cycles = 0
        self.misses = 0  # cycles whose work ran past their deadline
        self.skipped_periods = 0  # whole periods skipped because of overruns
        self.last_lateness = 0.0  # s
        self.last_compute = 0.0  # s
        self.last_missed = False
        self._late = _Ring(window)
        self._comp = _Ring(window)

    def start(self) -> None:
        """Set the time origin: the first period starts now."""
        self._t0 = self._clock()
        self._k = 0
        self._wake = self._t0

    @property
    def deadline(self) -> float:
        """End of the current period, monotonic seconds."""
        return self._t0 + (self._k + 1) * self.period

    @property
    def cycle_start(self) -> float:
        """Scheduled start of the current period, monotonic seconds."""
        return self._t0 + self._k * self.period

    def begin_cycle(self) -> float:
        """Mark the start of the cycle's work; returns the wake lateness (s, >= 0)."""
        self._wake = self._clock()
        self.last_lateness = max(0.0, self._wake - self.cycle_start)
        self._late.add(self.last_lateness)
        return self.last_lateness

    def keep_time(self) -> bool:
        """End of the cycle's work: account it and sleep to the next deadline.

        Returns True when the cycle missed its deadline.  Missed whole periods are skipped
        so the next cycle starts on the grid.
        """
        now = self._clock()
        self.last_compute = max(0.0, now - self._wake)
        self._comp.add(self.last_compute)
        self.cycles += 1
        deadline = self.deadline
        self.last_missed = now > deadline
        if self.last_missed:
            self.misses += 1
            # next start on the grid strictly after now
            k_next = math.floor((now - self._t0) / self.period) + 1
            self.skipped_periods += k_next - (self._k + 1)
            self._k = k_next
        else:
            self._k += 1
        wait = self.cycle_start - now
        if wait > 0:
            self._sleep(wait)
        return self.last_missed

    def stats(self) -> TimingStats:
        """Percentiles over the recent window; counters since start."""
        late, comp = self._late.values(), self._comp.values()
        return TimingStats(
            cycles=self.cycles,
            misses=self.misses,
            skipped_periods=self.skipped_periods,
            lateness_us_p50=_pct(late, 50),
            lateness_us_p99=_pct(late, 99),
            lateness_us_max=float(late.max()) * 1e6 if late.size else 0.0,
            compute_us_p50=_pct(comp, 50),
            compute_us_p99=_pct(comp, 99),
            compute_us_max=float(comp.max()) * 1e6 if comp.size else 0.0,
        )
