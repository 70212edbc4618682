"""What ``platoon.order: auto`` costs a daemon's cycle: the platoon decision before the
step (the predecessor's and the standby's newest plans and one other sender's, decoded and
noted) and the order's step on the estimate, against ``order: fixed`` (one predecessor),
with 1 to 32 trucks publishing a plan every cycle (docs/platoon.md, "Joining and
leaving").

    .venv/bin/python benchmarks/platoon_order_bench.py [--cycles 3000] [--json FILE [--key K]]

Each cycle every sender's plan arrives first (``on_sample``, Zenoh's thread in the
daemon: timed apart, per sample), then ``decide`` and the order's step (the hook the
controller calls between the estimate and the control law) are timed together.  The
modes run in interleaved blocks of 100 cycles, so a drifting load touches them alike.
Wall clock (``perf_counter_ns``): medians and p99, with the machine's load.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.results import machine, write_json  # noqa: E402
from truckd.config.truck import load_config  # noqa: E402
from truckd.control.estimator import Estimate  # noqa: E402
from truckd.control.platoon import encode_plan, kinematic_plan, platoon_control  # noqa: E402
from truckd.control.qp import ControlModel  # noqa: E402
from truckd.runtime.cycle import CompanionCycle  # noqa: E402
from truckd.runtime.platoon_link import DaemonPlatoon  # noqa: E402

PERIOD = 0.01
SENDERS = (1, 3, 10, 32)
BLOCK = 100
"""Cycles of one mode before the next mode's (interleaved)."""


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def _platoon(order: str, clock: _Clock) -> DaemonPlatoon:
    cfg = load_config()
    pcfg = replace(cfg.platoon, order=order, predecessor="s0")
    cyc = CompanionCycle(
        ControlModel(cfg.vehicle),
        platoon_control(cfg.control, pcfg),
        cfg.runtime.supervisor,
        cfg.ticks_per_rev,
        cfg.runtime.stop_ramp_v_per_s,
        time_budget=False,
    )
    return DaemonPlatoon("me", pcfg, cyc, wall=clock)


def _estimate() -> Estimate:
    return Estimate(
        v=1.0, speed_valid=True, gap=0.7, v_lead=1.0, lead_valid=True, lead_status="ok",
        gap_std=0.002, outliers=0, reinits=0, encoder_samples=1, range_samples=1,
        v_lead_std=0.02,
    )  # fmt: skip


class Run:
    """One DaemonPlatoon with ``n`` senders s0 <- s1 <- ... (this truck configured behind
    s0), driven a block of cycles at a time."""

    def __init__(self, order: str, n: int) -> None:
        self.order, self.n = order, n
        self.clock = _Clock()
        self.dp = _platoon(order, self.clock)
        self.hook = self.dp.cyc.controller.redecide
        self.est = _estimate()
        self.k = 0
        self.decide_ns: list[int] = []
        self.sample_ns: list[int] = []

    def cycles(self, count: int) -> None:
        dp, n = self.dp, self.n
        for _ in range(count):
            self.clock.t += PERIOD
            k = self.k
            self.k += 1
            payloads = [
                encode_plan(
                    replace(
                        kinematic_plan(self.clock.t, k, PERIOD, 1.0, 0.0, 40, f"s{i}"),
                        predecessor=f"s{i - 1}" if i else "",
                    )
                )
                for i in range(n)
            ]
            t0 = time.perf_counter_ns()
            for i, p in enumerate(payloads):
                if self.order == "auto":
                    dp.hearing.on_sample(f"truckd/s{i}/plan", p)
                elif i == 0 and dp.receiver is not None:
                    dp.receiver.on_payload(p)
            t1 = time.perf_counter_ns()
            dp.decide(None)
            if self.hook is not None:
                self.hook(self.est)
            t2 = time.perf_counter_ns()
            if k >= 100:  # past the first plans and the settling
                self.decide_ns.append(t2 - t1)
                self.sample_ns.append((t1 - t0) // n if self.order == "auto" else t1 - t0)

    def result(self) -> dict[str, Any]:
        d, s = np.asarray(self.decide_ns) / 1e3, np.asarray(self.sample_ns) / 1e3
        dp = self.dp
        return {
            "decide_us_p50": float(np.median(d)),
            "decide_us_p99": float(np.percentile(d, 99)),
            "per_sample_us_p50": float(np.median(s)),
            "mode_at_end": dp.decision.mode if dp.decision is not None else None,
            "predecessor": dp.predecessor,
            "errors": dp.errors,
        }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=3000, help="cycles per mode and sender count")
    ap.add_argument("--json", help="write the result here")
    ap.add_argument("--key", help="store it under this key of the --json file")
    args = ap.parse_args()
    result: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d"),
        "machine_start": machine(),
        "cycles": args.cycles,
        "runs": {},
    }
    runs = {f"{o}_{n}_senders": Run(o, n) for n in SENDERS for o in ("fixed", "auto")
            if o == "auto" or n == 1}  # fmt: skip
    for _ in range(max(1, (args.cycles + 100) // BLOCK)):
        for r in runs.values():
            r.cycles(BLOCK)
    for name, run in runs.items():
        r = result["runs"][name] = run.result()
        print(f"{name:18s}: decide + order p50 {r['decide_us_p50']:.1f} us, "
              f"p99 {r['decide_us_p99']:.1f} us; per sample {r['per_sample_us_p50']:.2f} us; "
              f"{r['mode_at_end']} behind {r['predecessor']}")  # fmt: skip
    result["machine_end"] = machine()
    if args.json:
        write_json(args.json, result, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
