"""The platoon at scale and on real links: 10 and 100 trucks against plan loss, delay and
clock offset.

For each case runs ``platoon-brake`` (simulated time; the figures do not depend on the
machine's load, only the run time does) and records the contract's spacing-error string
ratios (plain, and floored at the range sensor's noise: ``string_ratios``), the
acceleration ratios, the minimum gap, the CACC share and the run time.  The
links' timeout is the shipped 0.1 s, and 0.1 s after the slowest delivery with drawn
delays (``plan_timeout_s`` = 0.1 s + the largest delay).

    python benchmarks/platoon_scale.py --json benchmarks/platoon_scale.json [--trucks 10,100]
        [--cases LABEL,...] [--key KEY] [--seed 1] [--seeds 1,2,...] [--scenario platoon-brake]
        [--steady-start] [--spacing-rate]

With ``--key`` the run is stored under that key of the JSON file (the file's other keys
kept: earlier runs stay as they were measured); ``--cases`` runs only the cases whose
label starts with one of the given prefixes; ``--seeds`` runs each case once per seed,
``--scenario`` another platoon scenario (``--duration`` its length), ``--steady-start``
the trucks started in the steady state of the starting speed (``run_platoon``'s
``steady_start``: an unrecorded pre-roll), ``--spacing-rate`` the followers on
``platoon.spacing_rate`` (the spacing error's rate weighed, not the relative speed).
Each row also has
the pairwise ratios and every follower's spacing-error area (``integral of e dt`` from
3 s on, m s: what the time-headway policy passes on with a gain of 1, docs/platoon.md
"Mixed trucks").  The links' plans are held for the shipped
``plan_hold_s`` (a burst of lost plans ridden out on the last plan).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from dataclasses import replace
from typing import Any

import numpy as np
from results import machine, write_json

from truckd.config.truck import load_config
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon import SETTLE_S, PlatoonTrace, make_platoon_scenario, run_platoon

CASES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("ideal link", {}),
    ("30 % loss", {"loss": 0.3}),
    ("30 % loss in bursts", {"loss": 0.3, "burst_loss": True}),
    ("delay 0-50 ms", {"delay_s": (0.0, 0.05)}),
    ("clocks +-2 s, 100 ppm", {"clock_offset_s": 2.0, "clock_drift_ppm": 100.0}),
    (
        "bursts: 30 % loss in bursts, 0-50 ms, +-2 s, 100 ppm",
        {
            "loss": 0.3,
            "burst_loss": True,
            "delay_s": (0.0, 0.05),
            "clock_offset_s": 2.0,
            "clock_drift_ppm": 100.0,
        },
    ),
    (
        "all: 30 % loss, 0-50 ms, +-2 s, 100 ppm, mixed trucks",
        {
            "loss": 0.3,
            "delay_s": (0.0, 0.05),
            "clock_offset_s": 2.0,
            "clock_drift_ppm": 100.0,
            "mixed": True,
        },
    ),
    (
        "all with bursts: 30 % loss in bursts, 0-50 ms, +-2 s, 100 ppm, mixed trucks",
        {
            "loss": 0.3,
            "burst_loss": True,
            "delay_s": (0.0, 0.05),
            "clock_offset_s": 2.0,
            "clock_drift_ppm": 100.0,
            "mixed": True,
        },
    ),
)


def _areas(tr: PlatoonTrace) -> list[float]:
    """Every follower's spacing-error area ``integral of (gap - gap_ref) dt`` from
    :data:`SETTLE_S` on, as the ratios are taken (m s); a truck out of the lane (joining
    or gone) adds nothing."""
    t = np.asarray(tr.t)
    err = np.asarray(tr.gap, dtype=float)[:, 1:] - np.asarray(tr.gap_ref, dtype=float)[:, 1:]
    err = np.where(np.asarray(tr.lane)[:, 1:] == 0, err, np.nan)
    w = t >= SETTLE_S
    dt = float(t[1] - t[0])
    return [round(float(a), 5) for a in np.nansum(err[w], axis=0) * dt]


def _summary(m: dict[str, Any], seconds: float) -> dict[str, Any]:
    def mx(key: str) -> float:
        known = [r for r in m[key] if r is not None]
        return max(known) if known else float("nan")

    return {
        "collision": m["collision"],
        "min_gap_m": round(m["min_gap_m"], 4),
        "string_ratio_l2_max": round(mx("string_ratio_l2"), 3),
        "string_ratio_max_max": round(mx("string_ratio_max"), 3),
        "string_ratios_above_1": sum(
            r is not None and r > 1.0 for r in m["string_ratio_l2"] + m["string_ratio_max"]
        ),
        "string_ratio_floor_m": m["string_ratio_floor_m"],
        "string_ratio_l2_floored_max": round(mx("string_ratio_l2_floored"), 3),
        "string_ratio_max_floored_max": round(mx("string_ratio_max_floored"), 3),
        "accel_ratio_l2_max": round(mx("accel_ratio_l2"), 3),
        "accel_ratio_max_max": round(mx("accel_ratio_max"), 3),
        "spacing_error_max_first_last_m": [
            round(m["spacing_error_max_m"][0], 4),
            round(m["spacing_error_max_m"][-1], 4),
        ],
        "cacc_fraction_min": round(min(m["cacc_fraction"]), 3),
        "plans_lost_share": round(m["plans_lost"] / max(m["plans_sent"], 1), 3),
        "string_ratio_l2": [None if r is None else round(r, 3) for r in m["string_ratio_l2"]],
        "string_ratio_max": [None if r is None else round(r, 3) for r in m["string_ratio_max"]],
        "run_s": round(seconds, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--trucks", default="10,100")
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--cases", help="comma-separated label prefixes (default: every case)")
    ap.add_argument("--key", help="store the run under this key of the --json file")
    ap.add_argument("--seed", type=int, default=1, help="links, clocks and drawn trucks")
    ap.add_argument("--seeds", help="comma-separated seeds (instead of --seed)")
    ap.add_argument("--scenario", default="platoon-brake")
    ap.add_argument(
        "--steady-start",
        action="store_true",
        help="start in the steady state of the starting speed (the unrecorded pre-roll)",
    )
    ap.add_argument(
        "--spacing-rate",
        action="store_true",
        help="followers weigh the rate of their spacing error (platoon.spacing_rate; "
        "default: the configuration's)",
    )
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")] if args.seeds else [args.seed]
    load_at_start = round(os.getloadavg()[0], 2)
    prefixes = args.cases.split(",") if args.cases else [""]
    cfg = load_config()
    setup = SimSetup.from_config(cfg)
    rows: list[dict[str, Any]] = []
    for n in (int(x) for x in args.trucks.split(",")):
        for label, kw in CASES:
            if not any(label.startswith(p) for p in prefixes):
                continue
            hi = kw.get("delay_s", (0.02, 0.02))[1]
            timeout = 0.1 + hi if hi > 0.02 else cfg.platoon.plan_timeout_s
            pcfg = replace(
                cfg.platoon,
                plan_timeout_s=timeout,
                spacing_rate=args.spacing_rate or cfg.platoon.spacing_rate,
            )
            for seed in seeds:
                t0 = time.monotonic()
                m, tr = run_platoon(make_platoon_scenario(args.scenario), setup, pcfg, n,
                                    seed=seed, duration=args.duration,
                                    steady_start=args.steady_start, **kw)  # fmt: skip
                row = {"trucks": n, "case": label, "seed": seed,
                       **_summary(m, time.monotonic() - t0),
                       "spacing_error_area_m_s": _areas(tr)}  # fmt: skip
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        doc = {
            "what": f"{args.scenario}, simulated time: string ratios and gaps against the link",
            "date": datetime.date.today().isoformat(),
            "machine": machine(),
            "load_average_1min_at_start": load_at_start,
            "seed": seeds[0] if len(seeds) == 1 else seeds,
            "duration_s": args.duration,
            "plan_timeout_s": "0.1 s (shipped); 0.1 s + the largest delay with drawn delays",
            "plan_hold_s": cfg.platoon.plan_hold_s,
            "steady_start": args.steady_start,
            "spacing_rate": args.spacing_rate or cfg.platoon.spacing_rate,
            "rows": rows,
        }
        write_json(args.json, doc, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
