"""The machine's wake-up floor: a bare periodic sleeper, as the daemon's loop sleeps, with
no work at all (in the spirit of ``cyclictest``).

The thread takes the daemon's real-time set-up with the shipped configuration's priority
and wake-up latency (``truckd.runtime.realtime.setup_realtime``: SCHED_FIFO, mlockall and
the CPU wake-up latency request, when permitted) and sleeps to each deadline of a
fixed-rate grid; each wake-up's lateness is kept.
A wake-up later than ``period - compute`` would make the daemon's cycle miss its deadline
even if the cycle itself took only ``compute`` (its p50, ``--compute-us``): those are the
misses the machine makes, whatever the loop does. ``benchmarks/loop_bench.py`` at the
same rate, run before or after, gives the loop's own count.

    .venv/bin/python benchmarks/wakeup_floor.py [--rate 500] [--duration 60]
        [--compute-us 140] [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from results import KEY, machine, write_json

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from truckd.config.truck import load_config
from truckd.runtime.realtime import (
    release_cpu_latency,
    setup_realtime,
    unfreeze_gc,
)


def run(rate_hz: float, duration_s: float, compute_us: float) -> dict[str, Any]:
    """Sleep to each deadline of the grid for ``duration_s``; the lateness of each wake."""
    rt = load_config().runtime
    rep = setup_realtime(True, rt.rt_priority, rt.cpu_latency_us)
    period = 1.0 / rate_hz
    n = int(duration_s * rate_hz)
    late = np.empty(n)
    clock, sleep = time.monotonic, time.sleep
    t0 = clock()
    for k in range(n):
        target = t0 + (k + 1) * period
        wait = target - clock()
        if wait > 0:
            sleep(wait)
        late[k] = clock() - target
    release_cpu_latency()
    unfreeze_gc()
    budget = period - compute_us * 1e-6
    over = np.flatnonzero(late > budget)
    return {
        "rate_hz": rate_hz,
        "duration_s": duration_s,
        "sched_fifo": rep.sched_fifo,
        "cpu_latency_held": rep.cpu_latency_us is not None,
        "kernel_preemption": rep.kernel_preemption,
        "wakeups": n,
        "lateness_us_p50": float(np.percentile(late, 50) * 1e6),
        "lateness_us_p99": float(np.percentile(late, 99) * 1e6),
        "lateness_us_max": float(late.max() * 1e6),
        "compute_us_assumed": compute_us,
        "wakeups_too_late_for_the_cycle": int(over.size),
        "too_late": [
            {"t_s": round(float((k + 1) * period), 4), "lateness_us": round(float(late[k]) * 1e6)}
            for k in over[:50]
        ],
        "machine": machine(),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate", type=float, default=500.0, metavar="HZ")
    ap.add_argument("--duration", type=float, default=60.0, metavar="S")
    ap.add_argument(
        "--compute-us", type=float, default=140.0, metavar="US",
        help="the cycle's own time after its wake-up (the loop's compute p50)",
    )  # fmt: skip
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--key", metavar="NAME", help="store the run under NAME in --json's file")
    args = ap.parse_args()
    if not (1.0 <= args.rate <= 5000.0 and 0 < args.duration <= 3600):
        print("wakeup_floor: --rate in [1, 5000] Hz, --duration in (0, 3600] s", file=sys.stderr)
        return 2
    if not 0 <= args.compute_us < 1e6 / args.rate:
        print("wakeup_floor: --compute-us must be below the period", file=sys.stderr)
        return 2
    if args.key is not None and not KEY.fullmatch(args.key):
        print(f"wakeup_floor: --key {args.key!r}: name it what_YYYY-MM-DD", file=sys.stderr)
        return 2
    r = run(args.rate, args.duration, args.compute_us)
    print(
        f"wakeup_floor: {r['rate_hz']:.0f} Hz for {r['duration_s']:.0f} s, SCHED_FIFO "
        f"{r['sched_fifo']}: lateness p50 / p99 / max {r['lateness_us_p50']:.0f} / "
        f"{r['lateness_us_p99']:.0f} / {r['lateness_us_max']:.0f} us; wake-ups too late for a "
        f"{args.compute_us:.0f} us cycle: {r['wakeups_too_late_for_the_cycle']}"
    )
    if args.json:
        write_json(args.json, r, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
