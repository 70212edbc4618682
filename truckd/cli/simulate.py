"""``truckd simulate INPUT.csv --out OUT.csv``: open-loop run on a log's input."""

from __future__ import annotations

import argparse
from typing import Any

from truckd.cli.args import csv_file, report_notes, volts
from truckd.config.truck import load_config
from truckd.errors import InputError
from truckd.logfile import read_log, write_log
from truckd.modelfile import load_model_into
from truckd.outputs import check_distinct, guard_inputs
from truckd.sim.plant import simulate_open_loop


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("simulate", help="open-loop simulation on a log's input columns")
    p.add_argument("input", metavar="INPUT.csv", help="log with columns t and u")
    p.add_argument(
        "--out", required=True, type=csv_file, metavar="OUT.csv", help="where to write the log"
    )
    p.add_argument("--vbat", type=volts, metavar="V", help="supply voltage for a 'duty' log")
    p.add_argument("--config", help="configuration file (default: the shipped one)")
    p.add_argument("--model", metavar="FILE", help="model file written by identify/diagnose")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Refuses an output that is one of the inputs (see :func:`guard_inputs`)."""
    with guard_inputs(
        [args.input, args.config, args.model],
        [("--out", args.out)],
    ):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    check_distinct([("INPUT.csv", args.input), ("--out", args.out)])  # never over the input
    cfg = load_config(args.config)
    if args.model:
        cfg = load_model_into(cfg, args.model)
    log = read_log(args.input, require=("t", "u"), vbat=args.vbat)
    report_notes(log.notes)
    if len(log) < 2:
        raise InputError(f"{args.input}: need at least 2 data rows, found {len(log)}")
    v0 = float(log["v"][0]) if "v" in log else 0.0
    i0 = float(log["i"][0]) if "i" in log else None
    sim = simulate_open_loop(cfg.vehicle, log["t"], log["u"], cfg.plant, v0=v0, i0=i0)
    out = dict(log.columns)
    out["v"], out["i"], out["x"] = sim.v, sim.i, sim.x
    write_log(args.out, out)
    print(f"simulated {len(log)} samples ({log['t'][-1] - log['t'][0]:.3f} s) -> {args.out}")
    return 0
