"""``truckd identify LOG.csv [--config FILE] --out MODEL.yaml``: fit the seed model."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from truckd.cli.args import model_file, report_notes, volts
from truckd.config.truck import load_config
from truckd.ident.api import identify_log
from truckd.logfile import read_log
from truckd.modelfile import write_model


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("identify", help="fit the seed model to a measured log")
    p.add_argument("log", metavar="LOG.csv", help="log with columns t, u, v (optional i)")
    p.add_argument("--config", help="configuration file (starting values and bounds)")
    p.add_argument(
        "--out", required=True, type=model_file, metavar="MODEL.yaml", help="model file to write"
    )
    p.add_argument("--vbat", type=volts, metavar="V", help="supply voltage for a 'duty' log")
    p.set_defaults(run=run)


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    cfg = load_config(args.config)
    log = read_log(args.log, vbat=args.vbat)
    report_notes(log.notes)
    model = identify_log(log, cfg.vehicle, _progress)
    write_model(args.out, model)
    v = model.vehicle
    print(
        f"identified {args.log}: K_v={v.K_v:.5g} V s/rad, J_S={v.J_S:.4g} kg m^2, "
        f"K_coulomb={v.K_coulomb:.4g} N m, K_stiction={v.K_stiction:.4g} N m, "
        f"R_m={v.R_m:.4g} ohm -> {args.out}"
    )
    return 0
