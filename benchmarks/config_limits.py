"""The evidence behind two rules of the configuration check (docs/configuration.md): the
loop rate against the firmware's command timeout, and no bound on the MPC horizon.

Runs the closed loop in simulated time (no wall clock: the numbers do not depend on the
machine's load) with configurations built past the check (``dataclasses.replace``):

- the ``follow`` scenario at several ``control.rate_hz`` (the shipped configuration
  otherwise): gap error, and the share of cycles in which the controller commanded more
  than 0.1 V while the firmware applied none (its command timeout fired between commands);
- ``follow`` and ``lead-brake`` at 100 Hz with several ``control.horizon`` values.

Each row says whether the check accepts that configuration.

    .venv/bin/python benchmarks/config_limits.py [--json FILE]

``--json FILE`` writes ``{date, machine, load_avg, rows}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
from typing import Any

from truckd.config.cross import cross_section_problem
from truckd.config.truck import TruckConfig, load_config
from truckd.control.qp import ControlModel
from truckd.runtime.cycle import LOG_COLUMNS
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.scenarios import make_scenario

RATES_HZ = (8.0, 12.0, 20.0, 100.0)
HORIZONS = (3, 10, 40)
"""Steps (move blocks: min(8, horizon - 1))."""


def _row(cfg: TruckConfig, scenario: str) -> dict[str, Any]:
    setup = SimSetup(
        cfg.plant_vehicle, cfg.plant, cfg.control, ControlModel(cfg.vehicle),
        ticks_per_rev=cfg.link.encoder_ticks_per_rev, supervisor=cfg.runtime.supervisor,
        stop_ramp_v_per_s=cfg.runtime.stop_ramp_v_per_s,
    )  # fmt: skip
    metrics, trace = run_scenario(make_scenario(scenario, cfg.vehicle, cfg.control), setup)
    iu, ifw = LOG_COLUMNS.index("u"), LOG_COLUMNS.index("u_fw")
    driven = [r for r in trace.rows if abs(r[iu]) > 0.1]
    dropped = sum(abs(r[ifw]) < 0.01 for r in driven)
    return {
        "scenario": scenario,
        "rate_hz": cfg.control.rate_hz,
        "horizon": cfg.control.horizon,
        "accepted": cross_section_problem(cfg) is None,
        "gap_error_rms_m": metrics["gap_error_rms_m"],
        "min_gap_m": metrics["min_gap_m"],
        "collision": metrics["collision"],
        "commanded_not_applied_share": dropped / len(driven) if driven else None,
        "mode_time_s": metrics.get("mode_time_s"),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json")
    args = ap.parse_args()
    base = load_config()
    rows = []
    for rate in RATES_HZ:
        control = dataclasses.replace(base.control, rate_hz=rate)
        runtime = dataclasses.replace(base.runtime, stall_limit_s=max(0.05, 2.5 / rate))
        rows.append(_row(dataclasses.replace(base, control=control, runtime=runtime), "follow"))
        print(json.dumps(rows[-1]))
    for n in HORIZONS:
        control = dataclasses.replace(base.control, horizon=n, move_blocks=min(8, n - 1))
        for scenario in ("follow", "lead-brake"):
            rows.append(_row(dataclasses.replace(base, control=control), scenario))
            print(json.dumps(rows[-1]))
    if args.json:
        doc = {
            "date": datetime.date.today().isoformat(),
            "machine": f"{platform.machine()} {os.cpu_count()} cores",
            "load_avg": os.getloadavg()[0],
            "note": "simulated time: the metrics do not depend on the load",
            "rows": rows,
        }
        with open(args.json, "w", encoding="utf-8") as fh:
            fh.write(json.dumps(doc, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
