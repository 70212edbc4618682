"""The host's steal time, sampled beside a timing benchmark, and the deadline misses it
explains.

On a virtual machine the host may run other work on a vCPU's physical core: the guest's
threads then stand still, whatever their priority, and the kernel counts the time as
*steal* (``/proc/stat``, 8th value of each ``cpuN`` line, in USER_HZ ticks). A loop's
deadline miss during such a stall says nothing about the loop's own work.

``python benchmarks/host_steal.py PERIOD_S`` prints ``MONOTONIC_S STEAL_CPU0 STEAL_CPU1 ...``
each time a CPU's steal counter moves (polled every PERIOD_S, CLOCK_MONOTONIC, the clock
the daemon's log is stamped with), until SIGTERM. :func:`steal_times` reads those lines
back; :func:`misses_explained` matches them with a log's missed cycles.
"""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

USER_HZ = 100
"""Ticks per second of ``/proc/stat``'s counters (``getconf CLK_TCK`` on Linux)."""


def _read_steal() -> list[int]:
    with open("/proc/stat") as f:
        return [int(line.split()[8]) for line in f if line.startswith("cpu") and line[3] != " "]


def sample(period_s: float) -> None:
    """Print the steal counters each time one moves, until SIGTERM."""
    stop = False

    def on_term(_sig: int, _frame: Any) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_term)
    last = _read_steal()
    print(f"{time.monotonic():.6f} {' '.join(map(str, last))}", flush=True)
    while not stop:
        time.sleep(period_s)
        now = _read_steal()
        if now != last:
            print(f"{time.monotonic():.6f} {' '.join(map(str, now))}", flush=True)
            last = now


def steal_times(lines: Iterable[str]) -> tuple[np.ndarray, np.ndarray]:
    """The moments (monotonic s) the counters moved and the steal each added (s, all CPUs)."""
    rows = [[float(x) for x in line.split()] for line in lines if line.strip()]
    if len(rows) < 2:
        return np.zeros(0), np.zeros(0)
    a = np.array(rows)
    added = np.diff(a[:, 1:], axis=0).sum(axis=1) / USER_HZ
    return a[1:, 0], added


def misses_explained(
    starts: Sequence[float],
    ends: Sequence[float],
    steal_t: np.ndarray,
    margin_s: float,
    run_s: float,
) -> dict[str, Any]:
    """Missed cycles whose time (scheduled start to the end of their work, widened by
    ``margin_s`` after: the counter moves at the stolen CPU's next tick, seen at the
    next poll) holds a move of the steal counter; and how many would by chance (the
    share of the run such windows cover around the moves)."""
    hit = 0
    for s, e in zip(starts, ends, strict=True):
        if np.any((steal_t >= s) & (steal_t <= e + margin_s)):
            hit += 1
    n = len(starts)
    width = float(np.mean(np.subtract(ends, starts))) + margin_s if n else 0.0
    chance = min(1.0, len(steal_t) * width / run_s) if run_s > 0 else 0.0
    return {
        "misses": n,
        "with_host_steal": hit,
        "expected_by_chance": round(n * chance, 4),
        "steal_moves": len(steal_t),
    }


if __name__ == "__main__":
    sample(float(sys.argv[1]) if len(sys.argv) > 1 else 0.002)
