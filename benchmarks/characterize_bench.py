"""`truckd characterize` figures, on the in-process ``sim`` backend (the daemon's own loop in
real time, the simulated firmware):

- the routine with the defaults on the default truck: duration (checks and experiments,
  to rest) and distance driven;
- drawn trucks (tests/characterize_support.py: motor constant 2-3.5x and mass 2-5x the
  configured truck's, one hidden effect each: load, dead zone, battery sag, input delay),
  the configuration left at the default truck: the relative errors of kS, kV, kA and of the
  hidden effect's parameter, whether the effect was named, and the closed-loop gap RMS of
  `truckd sim` on the drawn plant with the configured model and with the diagnosed one.

Usage: python benchmarks/characterize_bench.py [--seeds N] [--json FILE]

Each run adds a key ``characterize_sim_<UTC date and time>`` to the JSON file.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from characterize_support import (  # noqa: E402
    CHARACTERIZE_FOR_DRAWN,
    EFFECT_RANGES,
    draw_truck,
    feedforward,
)

from truckd.cli.characterize import characterize  # noqa: E402
from truckd.config.truck import TruckConfig, load_config, parse_config  # noqa: E402
from truckd.control.qp import ControlModel  # noqa: E402
from truckd.modelfile import read_model  # noqa: E402
from truckd.sim.closed_loop import SimSetup, run_scenario  # noqa: E402
from truckd.sim.scenarios import make_scenario  # noqa: E402

SCENARIO = "follow"
SIM_S = 20.0


def _config(overrides: dict[str, Any]) -> TruckConfig:
    import yaml

    from truckd.config.truck import default_config_path

    base = yaml.safe_load(default_config_path().read_text())
    for k, v in overrides.items():
        base[k] = {**base.get(k, {}), **v} if isinstance(v, dict) else v
    return parse_config(yaml.safe_dump(base), "characterize_bench")


def _quiet(_: str) -> None:
    return None


def _gap_rms(cfg: TruckConfig, model: ControlModel) -> float:
    setup = SimSetup.from_config(cfg, model)
    m, _ = run_scenario(make_scenario(SCENARIO, cfg.plant_vehicle, cfg.control), setup, SIM_S)
    return float(m["gap_error_rms_m"])


def run_one(cfg: TruckConfig, tmp: Path) -> tuple[int, dict[str, Any]]:
    out = tmp / "out"
    t0 = time.monotonic()
    code = characterize(cfg, "sim", out, _quiet)
    wall = time.monotonic() - t0
    summary = json.loads((out / "summary.json").read_text())
    summary["wall_s"] = wall
    return code, summary


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=2, help="drawn trucks per effect")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "characterize_bench.json"))
    args = ap.parse_args()
    load_before = os.getloadavg()
    no_tel = {"runtime": {"backend": "sim", "telemetry": {"enabled": False}}}
    with tempfile.TemporaryDirectory() as tmp:
        code, s = run_one(_config(no_tel), Path(tmp))
    defaults = {
        "exit_code": code,
        "duration_s": s["duration_s"],
        "distance_m": s["distance_m"],
        "analysis_and_drive_wall_s": round(s["wall_s"], 1),
        "feedforward": s.get("feedforward"),
        "effects": [e["name"] for e in s.get("effects", [])],
        "fit_percent": s.get("fit_percent"),
    }
    print(f"defaults: {defaults}")
    configured = load_config().vehicle
    rows: list[dict[str, Any]] = []
    for effect in sorted(EFFECT_RANGES):
        for k in range(args.seeds):
            seed = 1000 + 17 * k + len(rows)
            truck = draw_truck(seed, configured, effect)
            cfg = _config(
                {**no_tel, "plant": truck.plant_section(), "characterize": CHARACTERIZE_FOR_DRAWN}
            )
            with tempfile.TemporaryDirectory() as tmp:
                code, s = run_one(cfg, Path(tmp))
                model = read_model(Path(tmp) / "out" / "model.yaml") if code == 0 else None
            row: dict[str, Any] = {
                "seed": seed,
                "effect": effect,
                "value": truck.value,
                "motor_factor": round(truck.motor_factor, 3),
                "mass_factor": round(truck.mass_factor, 3),
                "exit_code": code,
                "duration_s": s["duration_s"],
                "distance_m": s["distance_m"],
            }
            if model is not None:
                want = feedforward(truck.params(configured))
                got = s["feedforward"]
                row["ff_relerr"] = {n: abs(got[n] - want[n]) / want[n] for n in want}
                named = {e["name"]: e["params"] for e in s["effects"]}
                row["named"] = sorted(named)
                row["found"] = effect in named
                if effect in named:
                    row["effect_relerr"] = abs(named[effect][effect] - truck.value) / truck.value
                row["gap_rms_configured_m"] = _gap_rms(cfg, ControlModel(cfg.vehicle))
                row["gap_rms_identified_m"] = _gap_rms(
                    cfg, ControlModel(model.vehicle, model.effects)
                )
            print(json.dumps(row))
            rows.append(row)
    ok = [r for r in rows if "ff_relerr" in r]
    summary = {
        "trucks": len(rows),
        "completed": len(ok),
        "found": sum(1 for r in ok if r["found"]),
        "ff_relerr_median": {
            n: statistics.median(r["ff_relerr"][n] for r in ok) for n in ("kS", "kV", "kA")
        }
        if ok
        else None,
        "ff_relerr_max": {n: max(r["ff_relerr"][n] for r in ok) for n in ("kS", "kV", "kA")}
        if ok
        else None,
        "effect_relerr_median": statistics.median(
            r["effect_relerr"] for r in ok if "effect_relerr" in r
        )
        if any("effect_relerr" in r for r in ok)
        else None,
        "gap_rms_ratio_median": statistics.median(
            r["gap_rms_identified_m"] / r["gap_rms_configured_m"] for r in ok
        )
        if ok
        else None,
    }
    print(f"summary: {summary}")
    # a new key per run, dated (the earlier figures stay for comparison)
    key = time.strftime("characterize_sim_%Y-%m-%dT%H%MZ", time.gmtime())
    path = Path(args.json)
    doc: dict[str, Any] = json.loads(path.read_text()) if path.exists() else {}
    doc[key] = {
        "what": "truckd characterize on the in-process sim backend, real time",
        "scenario": SCENARIO,
        "sim_s": SIM_S,
        "seeds_per_effect": args.seeds,
        "defaults": defaults,
        "drawn": rows,
        "summary": summary,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "loadavg_before": load_before,
            "loadavg_after": os.getloadavg(),
        },
    }
    path.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"written: {path} [{key}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
