"""``truckd monitor [--connect ENDPOINT]``: live view of every vehicle reachable over Zenoh."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from truckd.cli.args import interval, monitor_duration
from truckd.runtime.monitor import run_monitor


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("monitor", help="live table of every vehicle reachable over Zenoh")
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help="Zenoh endpoint of a vehicle (repeatable; default tcp/127.0.0.1:7447)",
    )
    p.add_argument("--zenoh-config", default="", metavar="FILE", help="Zenoh JSON5 file")
    p.add_argument("--interval", type=interval, default=0.5, metavar="S", help="refresh period")
    p.add_argument("--duration", type=monitor_duration, metavar="S", help="stop after S s")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    connect = args.connect or ["tcp/127.0.0.1:7447"]
    run_monitor(
        connect,
        args.zenoh_config,
        sys.stdout,
        duration=args.duration,
        interval=args.interval,
        clear=sys.stdout.isatty(),
    )
    return 0
