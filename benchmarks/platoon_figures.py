"""String stability of the platoon: CACC against ACC alone at the same headway.

Runs ``platoon-brake`` and ``platoon-sine`` with 5 trucks for several headways, once with
plans (CACC) and once with every plan lost and the ACC headway set to the same value (ACC
alone), with and without the trucks' dead time; then ``platoon-comm-loss``.  Prints a
table and writes JSON (``--json FILE``).  Simulated time: the figures do not depend on the
machine's load (only the run time does).

    python benchmarks/platoon_figures.py --json benchmarks/platoon_figures.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from typing import Any

from truckd.config.truck import load_config
from truckd.control.platoon import PlatoonConfig
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon import make_platoon_scenario, run_platoon

HEADWAYS = (0.3, 0.4, 0.5, 0.6)
DELAYS = (0.0, 0.15)


def _run(name: str, pcfg: PlatoonConfig, loss: float, delay: float, n: int) -> dict[str, Any]:
    cfg = load_config()
    setup = SimSetup.from_config(cfg)
    sc = replace(make_platoon_scenario(name), input_delay=delay)
    m, _ = run_platoon(sc, setup, pcfg, n, loss=loss)
    return m


def _ratios(xs: list[float | None]) -> list[float | None]:
    return [None if x is None else round(x, 3) for x in xs]


def _stable(m: dict[str, Any]) -> bool:
    return all(r is None or r <= 1.0 for r in m["string_ratio_l2"] + m["string_ratio_max"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--trucks", type=int, default=5)
    args = ap.parse_args()
    rows: list[dict[str, Any]] = []
    t0 = time.monotonic()
    for delay in DELAYS:
        for name in ("platoon-brake", "platoon-sine"):
            for h in HEADWAYS:
                for policy in ("CACC", "ACC"):
                    pcfg = PlatoonConfig(cacc_headway=h, acc_headway=max(h, 1.1))
                    if policy == "ACC":
                        pcfg = replace(pcfg, acc_headway=h)
                    m = _run(name, pcfg, 0.0 if policy == "CACC" else 1.0, delay, args.trucks)
                    row = {
                        "scenario": name,
                        "dead_time_s": delay,
                        "headway_s": h,
                        "policy": policy,
                        "collision": m["collision"],
                        "min_gap_m": round(m["min_gap_m"], 4),
                        "string_ratio_l2": _ratios(m["string_ratio_l2"]),
                        "string_ratio_max": _ratios(m["string_ratio_max"]),
                        "spacing_error_max_m": [round(x, 4) for x in m["spacing_error_max_m"]],
                        "string_stable": _stable(m),
                    }
                    rows.append(row)
                    print(
                        f"{name:14s} dead {delay:.2f} s  h {h:.1f} s  {policy:4s}  "
                        f"l2 {row['string_ratio_l2']}  max {row['string_ratio_max']}  "
                        f"|e|max {row['spacing_error_max_m']}  min gap {row['min_gap_m']:.3f} m  "
                        f"{'stable' if row['string_stable'] else 'NOT stable'}",
                        flush=True,
                    )
    comm = _run("platoon-comm-loss", PlatoonConfig(), 0.0, 0.15, args.trucks)
    print(
        f"platoon-comm-loss: collision {comm['collision']}, min gap {comm['min_gap_m']:.3f} m, "
        f"first ACC {comm['first_acc_s']} s, CACC share {comm['cacc_fraction']}, "
        f"slowest deceleration {comm['min_accel_m_s2']} m/s^2 (per cycle)"
    )
    doc = {
        "trucks": args.trucks,
        "rows": rows,
        "comm_loss": comm,
        "run_time_s": round(time.monotonic() - t0, 1),
        "load_average": os.getloadavg(),
    }
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
