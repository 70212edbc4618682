"""``truckd identify LOG.csv [LOG.csv ...] [--gap S] [--config FILE] --out MODEL.yaml``:
fit the seed model to one or more logs (CSV, or WPILib SysId ``.json``)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from truckd.cli.args import model_file, report_notes, seconds, volts
from truckd.config.truck import load_config
from truckd.errors import InputError
from truckd.ident.api import (
    identify_log,
    identify_notes,
    position_unit,
    read_logs,
    require_physical,
)
from truckd.ident.data import runs_from_logs
from truckd.ident.physics import vehicle_problems
from truckd.ident.sysid import split_selector
from truckd.modelfile import write_model
from truckd.outputs import guard_inputs


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("identify", help="fit the seed model to measured logs")
    p.add_argument(
        "logs",
        nargs="+",
        metavar="LOG.csv",
        help="logs with columns t, u, v (optional i), or SysId FILE.json[:test,...]",
    )
    p.add_argument("--config", help="configuration file (starting values and bounds)")
    p.add_argument(
        "--out", required=True, type=model_file, metavar="MODEL.yaml", help="model file to write"
    )
    p.add_argument("--vbat", type=volts, metavar="V", help="supply voltage for a 'duty' log")
    add_gap_option(p)
    p.set_defaults(run=run)


def add_gap_option(p: Any) -> None:
    """``--gap S``: a time step longer than S seconds splits a log into runs."""
    p.add_argument(
        "--gap",
        type=seconds(0.0, 86400.0),
        metavar="S",
        help="a time step above S seconds is a pause between runs (default: 10 median steps)",
    )


def check_gap(gap: float | None) -> None:
    """Exit-2 error for a non-positive ``--gap``."""
    if gap is not None and not gap > 0.0:
        raise InputError(f"--gap: {gap!r}; expected a positive number of seconds")


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Refuses an output that is one of the inputs (see :func:`guard_inputs`)."""
    with guard_inputs(
        [*(split_selector(p)[0] for p in args.logs), args.config],
        [("--out", args.out)],
    ):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    check_gap(args.gap)
    cfg = load_config(args.config)
    logs = read_logs(args.logs, args.vbat)
    report_notes([n for lg in logs for n in lg.notes])
    model = identify_log(logs, cfg.vehicle, _progress, args.gap)
    require_physical(model, " ".join(args.logs), "fitted model")
    report_notes(identify_notes(logs, cfg.vehicle, model, args.gap))
    report_notes(
        f"the fitted model may not be physical: {p}"
        for p in vehicle_problems(model.vehicle, runs_from_logs(logs, args.gap))
    )
    write_model(args.out, model)
    v = model.vehicle
    from truckd.ident.linear import feedforward_of

    ff = feedforward_of(v)
    print(
        f"identified {' '.join(args.logs)}: K_v={v.K_v:.5g} V s/rad, J_S={v.J_S:.4g} kg m^2, "
        f"K_coulomb={v.K_coulomb:.4g} N m, K_stiction={v.K_stiction:.4g} N m, "
        f"R_m={v.R_m:.4g} ohm -> {args.out}"
    )
    pu = position_unit(logs)
    print(
        f"feedforward (SysId form): kS={ff.kS:.4g} V, kV={ff.kV:.4g} V s/{pu}, "
        f"kA={ff.kA:.4g} V s^2/{pu}"
    )
    return 0
