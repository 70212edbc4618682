"""``truckd diagnose LOG.csv [--validate LOG2.csv] [--config FILE] [--json FILE]
[--report DIR] [--out MODEL.yaml]``: what the simulation gets wrong, and why."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from truckd.cli.args import json_file, model_file, report_dir, report_notes, volts
from truckd.config.truck import load_config
from truckd.ident.api import diagnose_log, model_of
from truckd.logfile import read_log
from truckd.modelfile import model_text
from truckd.outputs import atomic_dir, check_distinct, write_set


def add_subparser(sub: Any) -> None:
    p = sub.add_parser("diagnose", help="name what the model is missing, extend it")
    p.add_argument("log", metavar="LOG.csv", help="log (t, u, v [, i]) or force log (t, F, x|v)")
    p.add_argument("--validate", metavar="LOG2.csv", help="validation log (same kind)")
    p.add_argument("--config", help="configuration file (starting values and bounds)")
    p.add_argument(
        "--json", type=json_file, metavar="FILE", help="write the result (CONTRACTS.md section 4)"
    )
    p.add_argument(
        "--report", type=report_dir, metavar="DIR", help="write index.html with plots here"
    )
    p.add_argument("--out", type=model_file, metavar="MODEL.yaml", help="write the extended model")
    p.add_argument("--vbat", type=volts, metavar="V", help="supply voltage for a 'duty' log")
    p.set_defaults(run=run)


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    check_distinct([("--out", args.out), ("--json", args.json)])
    cfg = load_config(args.config)
    log = read_log(args.log, vbat=args.vbat)
    val = read_log(args.validate, vbat=args.vbat) if args.validate else None
    report_notes(log.notes + (val.notes if val else []))
    diag = diagnose_log(log, cfg.vehicle, val, _progress)
    files: list[tuple[str, str | bytes]] = []
    if args.out:
        files.append((args.out, model_text(model_of(diag, args.log))))
    if args.json:
        files.append((args.json, json.dumps(diag.to_json(), indent=2) + "\n"))
    if args.report:
        from truckd.ident.report import write_report

        with atomic_dir(args.report) as tmp:  # published only if every output is written
            index = Path(args.report) / write_report(diag, tmp, args.log).name
            write_set(files)
        print(f"report: {index}")
    else:
        write_set(files)
    b, x = diag.baseline, diag.extended
    print(f"{diag.samples} samples ({diag.input} input)")
    print(f"seed model:     fit {b.fit_percent:7.2f} %  rmse {b.rmse:.4g}")
    for f in diag.effects:
        ps = ", ".join(f"{k}={v:.4g}" for k, v in f.params.items())
        print(f"  + {f.name:20s} {ps:28s} fit {f.fit_percent:7.2f} % ({f.fit_gain_percent:+.2f})")
    if not diag.effects:
        print("  no cause named: the seed model explains the data")
    print(f"extended model: fit {x.fit_percent:7.2f} %  rmse {x.rmse:.4g}")
    if b.force_relerr_percent is not None and x.force_relerr_percent is not None:
        print(
            f"force relative error: seed {b.force_relerr_percent:.3f} %, "
            f"extended {x.force_relerr_percent:.3f} %"
        )
    for a, c in diag.ambiguous:
        print(f"ambiguous: {a} / {c} (the data cannot tell them apart)")
    if diag.unexplained:
        print("unexplained: structure remains in the residual that no candidate explains")
    return 0
