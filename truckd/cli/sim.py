"""``truckd sim``: the controller drives the simulated truck through the simulated
firmware and the real protocol (reference section 1)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from truckd.cli.args import image_file, json_file, output_dir, plot_format, sim_duration
from truckd.cli.sim_platoon import add_platoon_arguments, check_platoon_only, run_platoon_cli
from truckd.config.truck import load_config
from truckd.control.effect_use import present_effects, startup_line
from truckd.control.qp import ControlModel
from truckd.errors import InputError, TruckdError
from truckd.modelfile import read_controller_model
from truckd.outputs import check_distinct, check_output_dir, ensure_dir, guard_inputs, write_set
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.mcap_export import mcap_paths, trace_mcap_bytes
from truckd.sim.platoon import PLATOON_SCENARIOS
from truckd.sim.report import json_safe, plot_image, table, trace_text
from truckd.sim.scenarios import SCENARIO_NAMES, make_scenario


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("sim", help="closed-loop simulation: controller + simulated firmware")
    p.add_argument(
        "--scenario",
        default="all",
        choices=(*SCENARIO_NAMES, *PLATOON_SCENARIOS, "all"),
        help="default: all (with --platoon: every platoon scenario)",
    )
    add_platoon_arguments(p)
    p.add_argument(
        "--duration",
        type=sim_duration,
        help="seconds, at most 1 h; a platoon's at most 10 800 truck-seconds over its "
        "trucks (default: the scenario's)",
    )
    p.add_argument("--realtime", action="store_true", help="pace the loop in wall-clock time")
    p.add_argument("--config", help="configuration file (default: the shipped one)")
    p.add_argument("--model", help="MODEL.yaml: the controller's model (the plant stays)")
    p.add_argument("--json", type=json_file, help="write the metrics as JSON to this file")
    p.add_argument(
        "--plot", type=image_file, help="write a plot (.png, .svg, .pdf) of gap, speeds, voltage"
    )
    p.add_argument(
        "--mcap", metavar="FILE|DIR", help="write MCAP (FILE.mcap, or DIR/<scenario>.mcap)"
    )
    p.add_argument(
        "--trace",
        metavar="DIR",
        type=output_dir("trace directory"),
        help="write each run's time series in the log format to DIR/<scenario>.csv",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Refuses an output that is one of the inputs (see :func:`guard_inputs`)."""
    with guard_inputs(
        [args.config, args.model],
        [("--json", args.json), ("--plot", args.plot), ("--mcap", args.mcap)],
    ):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    mcap_file = args.mcap is not None and Path(args.mcap).suffix == ".mcap"
    check_distinct(
        [("--json", args.json), ("--plot", args.plot), *([("--mcap", args.mcap)] * mcap_file)],
        [
            ("--trace", args.trace, (".csv",)),
            *([("--mcap", args.mcap, (".mcap",))] * (not mcap_file)),
        ],
    )
    if args.platoon is not None or args.scenario in PLATOON_SCENARIOS:
        return run_platoon_cli(args)
    check_platoon_only(args)
    cfg = load_config(args.config)
    if args.duration is not None and args.duration < cfg.control.period:
        raise InputError(
            f"--duration {args.duration:g}: shorter than one control period "
            f"({cfg.control.period:g} s at control.rate_hz {cfg.control.rate_hz:g}): no cycle "
            "would run"
        )
    if args.model:
        mf = read_controller_model(cfg, args.model)
        model, source = ControlModel(mf.vehicle, mf.effects), f"model file {args.model}"
    else:
        model, source = ControlModel(cfg.vehicle), "configured vehicle"
    note = startup_line(model.effects)
    if note is not None:
        print(f"truckd sim: {note}", file=sys.stderr)
    # checked now, created when the traces are written (a run that fails leaves none)
    trace_dir = check_output_dir(args.trace, "trace directory") if args.trace else None
    setup = SimSetup.from_config(cfg, model)
    names = SCENARIO_NAMES if args.scenario == "all" else (args.scenario,)
    mcaps = mcap_paths(args.mcap, names) if args.mcap is not None else {}
    results, traces = [], []
    for name in names:
        metrics, trace = run_scenario(
            make_scenario(name, cfg.vehicle, cfg.control), setup, args.duration, args.realtime
        )
        results.append(json_safe(metrics))
        traces.append((name, trace))
    effects = ", ".join(present_effects(model.effects)) or "none"
    print(
        f"controller model: {source} (effects: {effects}); plant effects: "
        f"{', '.join(present_effects(cfg.plant.effects)) or 'none'}"
    )
    print(table(results))
    files: list[tuple[str | Path, str | bytes]] = []
    if args.json:
        doc: object = results if args.scenario == "all" else results[0]
        files.append((args.json, json.dumps(doc, indent=2, allow_nan=False) + "\n"))
    if args.plot:
        files.append((args.plot, plot_image(traces, plot_format(args.plot))))
    for name, trace in traces if mcaps else ():
        every = cfg.runtime.recorder.mcap_plan_every  # as the daemon records plans
        files.append((mcaps[name], trace_mcap_bytes(cfg.vehicle_id, name, trace, every)))
    if trace_dir is not None:
        ensure_dir(trace_dir, "trace directory")
        for name, trace in traces:
            files.append((trace_dir / f"{name}.csv", trace_text(trace)))
    write_set(files)  # all or nothing: JSON, plot, MCAP files and traces
    crashed = [r["scenario"] for r in results if r["collision"]]
    if crashed:
        raise TruckdError(f"collision in: {', '.join(crashed)}")
    return 0
