"""``truckd params [--config FILE] --json``: the vehicle parameters in use."""

from __future__ import annotations

import argparse
import json
from typing import Any

from truckd.config.truck import load_config


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("params", help="print the vehicle parameters")
    p.add_argument("--config", help="configuration file (default: the shipped one)")
    p.add_argument("--json", action="store_true", help="print JSON (docs/reference.md section 2)")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    params = load_config(args.config).vehicle.as_dict()
    if args.json:
        print(json.dumps(params, indent=2))
    else:
        width = max(len(k) for k in params)
        for k, val in params.items():
            print(f"{k:<{width}}  {val:.6g}")
    return 0
