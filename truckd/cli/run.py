"""``truckd run --config FILE [--backend sim|serial|can] [--duration S]``: the daemon."""

from __future__ import annotations

import argparse
import logging
import sys
from typing import Any

from truckd.cli.args import run_duration
from truckd.config.truck import load_config
from truckd.control.effect_use import startup_line
from truckd.control.qp import ControlModel
from truckd.io.backends import BACKEND_NAMES
from truckd.modelfile import read_controller_model
from truckd.runtime.daemon import Daemon


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("run", help="the daemon (as systemd starts it on the car)")
    p.add_argument("--config", required=True, help="configuration file (truck.yaml)")
    p.add_argument("--backend", choices=BACKEND_NAMES, help="override runtime.backend")
    p.add_argument(
        "--duration", type=run_duration, metavar="S", help="stop cleanly after S seconds"
    )
    p.add_argument(
        "--model", metavar="MODEL.yaml", help="the controller's model (identify/diagnose output)"
    )
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=args.log_level,
        stream=sys.stderr,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    cfg = load_config(args.config)
    model = None
    if args.model:
        mf = read_controller_model(cfg, args.model)
        model = ControlModel(mf.vehicle, mf.effects)
        note = startup_line(mf.effects)
        if note is not None:
            logging.getLogger("truckd").warning("%s", note)
    return Daemon(cfg, args.backend, duration=args.duration, model=model).run()
