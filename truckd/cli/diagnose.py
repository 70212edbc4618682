"""``truckd diagnose LOG.csv [LOG.csv ...] [--validate LOG.csv ...] [--gap S] [--config FILE]
[--json FILE] [--report DIR] [--out MODEL.yaml] [--jobs N]``: what the simulation gets wrong,
and why.

Logs are CSV (reference section 3) or WPILib SysId ``FILE.json[:test,...]``."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from truckd.cli.args import jobs, json_file, model_file, report_dir, report_notes, volts
from truckd.cli.identify import add_gap_option, check_gap
from truckd.config.truck import load_config
from truckd.ident.api import diagnose_log, model_of, read_logs, require_physical
from truckd.ident.sysid import split_selector
from truckd.modelfile import model_text
from truckd.outputs import atomic_dir, check_distinct, guard_inputs, write_set
from truckd.workers import usable_cpus

DIAGNOSE_MAX_ROWS = 360_000
"""Rows of one log diagnosed at most (an hour at 100 Hz): a longer log is read whole (every
row checked, memory for the rows kept only) and diagnosed on 8 evenly spread stretches
of 45 000 rows, each a run, so memory and time stay bounded (docs/diagnosis.md)."""


DEFAULT_JOBS_MAX = 4
"""Worker processes ``--jobs`` defaults to at most: a stage has some 6-13 independent
fits of unequal length, and each process holds its own copy of what it changes."""


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("diagnose", help="name what the model is missing, extend it")
    p.add_argument(
        "logs",
        nargs="+",
        metavar="LOG.csv",
        help="logs (t, u, v [, i]), force logs (t, F, x|v) or SysId FILE.json[:test,...]",
    )
    p.add_argument("--validate", nargs="+", metavar="LOG.csv", help="validation logs (same kind)")
    p.add_argument("--config", help="configuration file (starting values and bounds)")
    p.add_argument(
        "--json", type=json_file, metavar="FILE", help="write the result (docs/reference.md 4)"
    )
    p.add_argument(
        "--report", type=report_dir, metavar="DIR", help="write index.html with plots here"
    )
    p.add_argument("--out", type=model_file, metavar="MODEL.yaml", help="write the extended model")
    p.add_argument("--vbat", type=volts, metavar="V", help="supply voltage for a 'duty' log")
    add_gap_option(p)
    p.add_argument(
        "--jobs",
        type=jobs,
        metavar="N",
        help="fit the candidates on N processes (default: the CPUs this process may use, "
        "at most 4; 1: one after another; the result is the same)",
    )
    p.set_defaults(run=run)


LARGE_LOG_BYTES = 20_000_000
"""A log this large takes seconds to read: the command says it is reading it."""


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    """Refuses an output that is one of the inputs (see :func:`guard_inputs`)."""
    with guard_inputs(
        [*(split_selector(p)[0] for p in [*args.logs, *(args.validate or [])]), args.config],
        [("--json", args.json), ("--out", args.out), ("--report", args.report)],
    ):
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    check_distinct([("--out", args.out), ("--json", args.json)], [("--report", args.report, ())])
    check_gap(args.gap)
    cfg = load_config(args.config)
    for path in dict.fromkeys(split_selector(p)[0] for p in [*args.logs, *(args.validate or [])]):
        size = os.path.getsize(path) if os.path.isfile(path) else 0
        if size > LARGE_LOG_BYTES:  # a minute's silence otherwise (3 million rows: ~25 s)
            _progress(f"reading {path} ({size / 1e6:.0f} MB)")
    logs = read_logs(args.logs, args.vbat, DIAGNOSE_MAX_ROWS)
    val = read_logs(args.validate, args.vbat, DIAGNOSE_MAX_ROWS) if args.validate else None
    report_notes([n for lg in [*logs, *(val or [])] for n in lg.notes])
    workers = args.jobs if args.jobs is not None else min(usable_cpus(), DEFAULT_JOBS_MAX)
    diag = diagnose_log(logs, cfg.vehicle, val, _progress, args.gap, workers)
    name = " ".join(args.logs)
    files: list[tuple[str, str | bytes]] = []
    if args.out:
        model = require_physical(model_of(diag, name), name, "extended model")
        files.append((args.out, model_text(model)))
    if args.json:
        files.append((args.json, json.dumps(diag.to_json(), indent=2) + "\n"))
    if args.report:
        from truckd.ident.report import write_report

        with atomic_dir(args.report) as tmp:  # published only if every output is written
            index = Path(args.report) / write_report(diag, tmp, name).name
            write_set(files)
        print(f"report: {index}")
    else:
        write_set(files)
    b, x = diag.baseline, diag.extended
    print(f"{diag.samples} samples in {diag.runs} run(s) ({diag.input} input)")
    ls = diag.least_squares
    if ls is not None and ls.get("fit_percent") is not None:
        u = diag.units()[1:]
        print(
            f"least squares:  fit {ls['fit_percent']:7.2f} %  (SysId's kS={ls['kS']:.4g} "
            f"{u[0]}, kV={ls['kV']:.4g} {u[1]}, kA={ls['kA']:.4g} {u[2]})"
        )
    print(f"seed model:     fit {b.fit_percent:7.2f} %  rmse {b.rmse:.4g}")
    for f in diag.effects:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in f.params.items())
        print(f"  + {f.name:20s} {ps:28s} fit {f.fit_percent:7.2f} % ({f.fit_gain_percent:+.2f})")
    for r in diag.rejected:
        print(f"  best fit not accepted: {r.name}: {r.reason}")
    if not diag.effects:
        if diag.explains:
            print("  no cause named: the residual is white at the noise level")
        else:
            print("  no cause named among the candidates")
    print(f"extended model: fit {x.fit_percent:7.2f} %  rmse {x.rmse:.4g}")
    if diag.fit_ceiling is not None:
        print(
            f"noise ceiling:  fit {diag.fit_ceiling:7.2f} %  (a model that leaves only the "
            "speed's measurement noise)"
        )
    if b.force_relerr_percent is not None and x.force_relerr_percent is not None:
        print(
            f"force relative error: seed {b.force_relerr_percent:.3f} %, "
            f"extended {x.force_relerr_percent:.3f} %"
        )
    for a, c in diag.ambiguous:
        print(f"ambiguous: {a} / {c} (the data cannot tell them apart)")
    if diag.unexplained:
        print(
            f"unexplained: structure remains in the residual that no candidate explains "
            f"(fit {x.fit_percent:.1f} %)"
        )
    elif diag.explains:
        print("the model explains the data: its residual is white at the noise level")
    for note in diag.alerts:
        print(f"note: {note}")
    ff = x.feedforward
    if ff is not None:
        print(
            f"feedforward (SysId form): kS={ff['kS']:.4g} V, kV={ff['kV']:.4g} "
            f"{diag.units()[2]}, kA={ff['kA']:.4g} {diag.units()[3]}"
        )
    return 0
