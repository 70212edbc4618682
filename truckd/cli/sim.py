"""``truckd sim``: the controller drives the simulated truck through the simulated
firmware and the real protocol (CONTRACTS.md section 1)."""

from __future__ import annotations

import argparse
import json
from typing import Any

from truckd.cli.args import image_file, json_file, plot_format, sim_duration
from truckd.config.truck import load_config
from truckd.control.qp import ControlModel
from truckd.errors import TruckdError
from truckd.modelfile import read_model
from truckd.outputs import check_distinct, write_set
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.report import json_safe, plot_image, table
from truckd.sim.scenarios import SCENARIO_NAMES, make_scenario


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("sim", help="closed-loop simulation: controller + simulated firmware")
    p.add_argument(
        "--scenario", default="all", choices=(*SCENARIO_NAMES, "all"), help="default: all"
    )
    p.add_argument(
        "--duration", type=sim_duration, help="seconds, at most 24 h (default: the scenario's)"
    )
    p.add_argument("--realtime", action="store_true", help="pace the loop in wall-clock time")
    p.add_argument("--config", help="configuration file (default: the shipped one)")
    p.add_argument("--model", help="MODEL.yaml: the controller's model (the plant stays)")
    p.add_argument("--json", type=json_file, help="write the metrics as JSON to this file")
    p.add_argument(
        "--plot", type=image_file, help="write a plot (.png, .svg, .pdf) of gap, speeds, voltage"
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    check_distinct([("--json", args.json), ("--plot", args.plot)])
    cfg = load_config(args.config)
    if args.model:
        mf = read_model(args.model)
        model, source = ControlModel(mf.vehicle, mf.effects), f"model file {args.model}"
    else:
        model, source = ControlModel(cfg.vehicle), "configured vehicle"
    setup = SimSetup(
        cfg.vehicle, cfg.plant, cfg.control, model, ticks_per_rev=cfg.link.encoder_ticks_per_rev
    )
    names = SCENARIO_NAMES if args.scenario == "all" else (args.scenario,)
    results, traces = [], []
    for name in names:
        metrics, trace = run_scenario(
            make_scenario(name, cfg.vehicle, cfg.control), setup, args.duration, args.realtime
        )
        results.append(json_safe(metrics))
        traces.append((name, trace))
    effects = ", ".join(model.effects.active()) or "none"
    print(
        f"controller model: {source} (effects: {effects}); plant effects: "
        f"{', '.join(cfg.plant.effects.active()) or 'none'}"
    )
    print(table(results))
    files: list[tuple[str, str | bytes]] = []
    if args.json:
        doc: object = results if args.scenario == "all" else results[0]
        files.append((args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n"))
    if args.plot:
        files.append((args.plot, plot_image(traces, plot_format(args.plot))))
    write_set(files)  # all or nothing
    crashed = [r["scenario"] for r in results if r["collision"]]
    if crashed:
        raise TruckdError(f"collision in: {', '.join(crashed)}")
    return 0
