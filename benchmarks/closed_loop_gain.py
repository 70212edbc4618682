"""Closing the loop: the controller with the seed model against the controller with the
model ``diagnose`` extracted from a log of the same truck.

For each effect: the simulated truck (plant) has the effect switched on; an open-loop
log of it (random excitation, noise) goes through ``truckd diagnose --out MODEL.yaml``;
then ``truckd sim`` runs each scenario twice on that plant, the controller using the
configured (seed) model, then ``--model MODEL.yaml``.  Reported: gap error RMS (after
the first 5 s) with both.

    .venv/bin/python benchmarks/closed_loop_gain.py [--json FILE] [--scenarios a,b]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import yaml

from truckd.cli.main import main as truckd
from truckd.config.truck import default_config_path, load_config
from truckd.ident.synth import plant_log, with_effect
from truckd.logfile import write_log

CASES = {
    "load_force": 5.0,  # N: a 15 % grade for a 3.5 kg truck, or a trailer
    "input_delay": 0.06,  # s
    "battery_sag": 0.2,  # ohm
    "dead_zone": 1.2,  # V
}


def _sim(cfg: Path, scenario: str, out: Path, model: Path | None) -> dict[str, Any]:
    argv = ["sim", "--config", str(cfg), "--scenario", scenario, "--json", str(out)]
    if model is not None:
        argv += ["--model", str(model)]
    with contextlib.redirect_stdout(io.StringIO()):
        code = truckd(argv)
    if code != 0:
        raise SystemExit(f"truckd {' '.join(argv)} exited {code}")
    data = json.loads(out.read_text())
    return data[0] if isinstance(data, list) else data  # type: ignore[no-any-return]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--scenarios", default="follow,stop-and-go,lead-brake")
    args = ap.parse_args()
    base = yaml.safe_load(default_config_path().read_text())
    p = load_config().vehicle
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        for name, value in CASES.items():
            cfg = dict(base)
            cfg["plant"] = dict(base["plant"])
            cfg["plant"]["effects"] = dict(base["plant"]["effects"], **{name: value})
            cfg_path = d / f"{name}.yaml"
            cfg_path.write_text(yaml.safe_dump(cfg))
            log = plant_log(p, with_effect(name, value), seed=2026, n=6000)
            write_log(d / f"{name}.csv", log.columns)
            model = d / f"{name}_model.yaml"
            with (
                contextlib.redirect_stdout(io.StringIO()),
                contextlib.redirect_stderr(io.StringIO()),
            ):
                code = truckd(
                    [
                        "diagnose",
                        str(d / f"{name}.csv"),
                        "--out",
                        str(model),
                        "--json",
                        str(d / f"{name}.json"),
                    ]
                )
            if code != 0:
                raise SystemExit(f"diagnose failed on {name}")
            found = json.loads((d / f"{name}.json").read_text())["effects"]
            for sc in args.scenarios.split(","):
                seed_m = _sim(cfg_path, sc, d / "a.json", None)
                ext_m = _sim(cfg_path, sc, d / "b.json", model)
                rows.append(
                    {
                        "effect": name,
                        "value": value,
                        "found": found,
                        "scenario": sc,
                        "gap_rms_seed_m": seed_m["gap_error_rms_m"],
                        "gap_rms_extended_m": ext_m["gap_error_rms_m"],
                        "min_gap_seed_m": seed_m["min_gap_m"],
                        "min_gap_extended_m": ext_m["min_gap_m"],
                        "collision_seed": seed_m["collision"],
                        "collision_extended": ext_m["collision"],
                    }
                )
                r = rows[-1]
                print(
                    f"{name:12s} {sc:12s} gap RMS seed {r['gap_rms_seed_m']:.4f} m, "
                    f"extended {r['gap_rms_extended_m']:.4f} m  "
                    f"(found {[f['name'] for f in found]})",
                    flush=True,
                )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
