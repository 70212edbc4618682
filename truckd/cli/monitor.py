"""``truckd monitor [--connect ENDPOINT] [--foxglove [PORT]]``: live view of every vehicle
reachable over Zenoh, as a table or served to Foxglove (docs/foxglove.md)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from truckd.cli.args import interval, monitor_duration
from truckd.errors import InputError
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
    p.add_argument(
        "--foxglove",
        nargs="?",
        type=int,
        const=8765,
        metavar="PORT",
        help="serve state, health and plan of every vehicle to Foxglove over WebSocket "
        "instead of the table (port default 8765; 0: any free port)",
    )
    p.add_argument(
        "--foxglove-host",
        default="127.0.0.1",
        metavar="ADDR",
        help="address the Foxglove server binds (default 127.0.0.1: this machine only)",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    connect = args.connect or ["tcp/127.0.0.1:7447"]
    if args.foxglove is not None:
        if not 0 <= args.foxglove <= 65535:
            raise InputError(f"--foxglove {args.foxglove}: expected a TCP port in [0, 65535]")
        from truckd.runtime.foxglove_relay import FoxgloveRelay, run_relay

        relay = FoxgloveRelay(
            connect, args.zenoh_config, host=args.foxglove_host, port=args.foxglove
        )
        run_relay(relay, sys.stdout, duration=args.duration, interval=max(args.interval, 5.0))
        return 0
    run_monitor(
        connect,
        args.zenoh_config,
        sys.stdout,
        duration=args.duration,
        interval=args.interval,
        clear=sys.stdout.isatty(),
    )
    return 0
