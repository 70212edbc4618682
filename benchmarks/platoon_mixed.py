"""Drawn trucks (``truckd sim --platoon N --mixed``): the controllers on the drawn trucks'
true parameters against the controllers on the models each truck's own identification
drive diagnoses (:mod:`truckd.cli.platoon_diagnosis`).

For each seed and scenario (``platoon-brake`` 12 s, ``platoon-sine`` 15 s) runs the same
drawn platoon twice on the links of the existing figures (``platoon_scale.py``'s "all"
case: 30 % of the plans lost at random, delays drawn in 0-50 ms, clocks +-2 s / 100 ppm,
``plan_timeout_s`` 0.15 s), once with each kind of controller model, and records the
string ratios (``platoon_scale.py``'s summary, the pairwise ratios and the spacing-error
areas) and, for the diagnosed models, how far each is from its truck (feedforward
constants, mechanical time constant, dead time, effects named).  Simulated time: the
figures do not depend on the load; the run times do.

    nice -n 10 python benchmarks/platoon_mixed.py --json benchmarks/platoon_mixed.json
        [--trucks 10] [--seeds 1,2,3,4,5,6] [--key KEY] [--diagnosis-cache DIR]
        [--scenarios platoon-brake,platoon-sine] [--models true,diagnosed]
        [--q-rel-speed W] [--diagnosed-disturbance-gain G]

``--scenarios`` and ``--models`` run a part of the grid; ``--q-rel-speed`` replaces the
configured follower's relative-speed weight (``platoon.q_rel_speed``) and
``--diagnosed-disturbance-gain`` the offset-free gain of a controller on a diagnosed model
(``DIAGNOSED_DISTURBANCE_GAIN``), for the experiments that vary them (the JSON records
both as run).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from platoon_scale import CASES, _areas, _summary
from results import machine, write_json

import truckd.sim.platoon_truck as platoon_truck
from truckd.cli.platoon_diagnosis import DiagnosedControllers
from truckd.config.truck import load_config
from truckd.sim.closed_loop import SimSetup
from truckd.sim.platoon import make_platoon_scenario, run_platoon
from truckd.workers import usable_cpus

SCENARIOS = (("platoon-brake", 12.0), ("platoon-sine", 15.0))
LINK_CASE = "all: 30 % loss, 0-50 ms, +-2 s, 100 ppm, mixed trucks"


def _model_errors(diag: list[dict[str, Any]]) -> dict[str, Any]:
    """The largest errors of the diagnosed models over the trucks."""

    def worst(key: str) -> float:
        return float(max(abs(d["feedforward_relerr"][key]) for d in diag))

    return {
        "per_truck": [
            {
                **{k: round(v, 4) for k, v in d["feedforward_relerr"].items()},
                "tau_m": round(d["tau_m_s"] / d["tau_m_true_s"] - 1.0, 4),
                "effects": {k: round(v, 4) for k, v in d["effects"].items()},
            }
            for d in diag
        ],
        "feedforward_relerr_max": {k: round(worst(k), 4) for k in ("kS", "kV", "kA")},
        "tau_m_relerr_max": round(max(abs(d["tau_m_s"] / d["tau_m_true_s"] - 1) for d in diag), 4),
        "input_delay_s": [round(d["input_delay_s"], 4) for d in diag],
        "effects_named": [sorted(k for k in d["effects"] if k != "input_delay") for d in diag],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--trucks", type=int, default=10)
    ap.add_argument("--seeds", default="1,2,3,4,5,6")
    ap.add_argument("--key", help="store the run under this key of the --json file")
    ap.add_argument("--diagnosis-cache", metavar="DIR", help="keep the diagnosed models here")
    ap.add_argument("--scenarios", default=",".join(name for name, _ in SCENARIOS))
    ap.add_argument("--models", default="true,diagnosed")
    ap.add_argument("--q-rel-speed", type=float, help="instead of platoon.q_rel_speed")
    ap.add_argument("--diagnosed-disturbance-gain", type=float,
                    help="instead of DIAGNOSED_DISTURBANCE_GAIN")  # fmt: skip
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")]
    scenarios = [(n, d) for n, d in SCENARIOS if n in args.scenarios.split(",")]
    kinds = [k for k in ("true", "diagnosed") if k in args.models.split(",")]
    if args.diagnosed_disturbance_gain is not None:
        platoon_truck.DIAGNOSED_DISTURBANCE_GAIN = args.diagnosed_disturbance_gain
    load_at_start = round(os.getloadavg()[0], 2)
    cfg = load_config()
    setup = SimSetup.from_config(cfg)
    kw = dict(CASES)[LINK_CASE]
    pcfg = replace(cfg.platoon, plan_timeout_s=0.1 + kw["delay_s"][1])
    if args.q_rel_speed is not None:
        pcfg = replace(pcfg, q_rel_speed=args.q_rel_speed)
    cache = Path(args.diagnosis_cache) if args.diagnosis_cache else None
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    diagnosed = DiagnosedControllers(cfg, cache_dir=cache, workers=min(usable_cpus(), 4))
    spent = [0.0]

    def timed(base: SimSetup, trucks: Any) -> Any:
        t = time.monotonic()
        out = diagnosed(base, trucks)
        spent[0] += time.monotonic() - t
        return out

    rows: list[dict[str, Any]] = []
    for seed in seeds:
        for name, duration in scenarios:
            for models in kinds:
                t0, before = time.monotonic(), spent[0]
                ctl = timed if models == "diagnosed" else None
                m, tr = run_platoon(make_platoon_scenario(name), setup, pcfg, args.trucks,
                                    seed=seed, duration=duration, controllers=ctl,
                                    **kw)  # fmt: skip
                row: dict[str, Any] = {
                    "scenario": name,
                    "seed": seed,
                    "models": models,
                    **_summary(m, time.monotonic() - t0),
                    "spacing_error_area_m_s": _areas(tr),
                }
                if m.get("trucks_drawn"):
                    row["trucks_drawn"] = m["trucks_drawn"]
                if "trucks_diagnosed" in m:
                    row["diagnosis_s"] = round(spent[0] - before, 1)
                    row["model_errors"] = _model_errors(m["trucks_diagnosed"])
                rows.append(row)
                print(json.dumps(row), flush=True)
    if args.json:
        doc = {
            "what": "drawn trucks, simulated time: string ratios with the controllers on the "
            "true parameters and on each truck's diagnosed model",
            "date": datetime.date.today().isoformat(),
            "machine": machine(),
            "load_average_1min_at_start": load_at_start,
            "trucks": args.trucks,
            "link": LINK_CASE,
            "plan_timeout_s": pcfg.plan_timeout_s,
            "plan_hold_s": pcfg.plan_hold_s,
            "q_rel_speed": pcfg.q_rel_speed,
            "diagnosed_disturbance_gain": platoon_truck.DIAGNOSED_DISTURBANCE_GAIN,
            "trucks_diagnosed_per_process": diagnosed.diagnosed,
            "rows": rows,
        }
        write_json(args.json, doc, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
