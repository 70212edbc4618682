"""``truckd diagnose LOG.csv [LOG.csv ...] [--validate LOG.csv ...] [--gap S] [--config FILE]
[--json FILE] [--report DIR] [--out MODEL.yaml]``: what the simulation gets wrong, and why.

Logs are CSV (CONTRACTS.md section 3) or WPILib SysId ``FILE.json[:test,...]``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from truckd.cli.identify import add_gap_option, check_gap
from truckd.config.truck import load_config
from truckd.ident.api import diagnose_log, model_of, read_logs
from truckd.modelfile import write_model


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
    p.add_argument("--json", metavar="FILE", help="write the result (CONTRACTS.md section 4)")
    p.add_argument("--report", metavar="DIR", help="write index.html with plots here")
    p.add_argument("--out", metavar="MODEL.yaml", help="write the extended model")
    add_gap_option(p)
    p.set_defaults(run=run)


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    check_gap(args.gap)
    cfg = load_config(args.config)
    logs = read_logs(args.logs)
    val = read_logs(args.validate) if args.validate else None
    diag = diagnose_log(logs, cfg.vehicle, val, _progress, args.gap)
    name = " ".join(args.logs)
    if args.out:
        write_model(args.out, model_of(diag, name))
    if args.json:
        Path(args.json).write_text(json.dumps(diag.to_json(), indent=2) + "\n", encoding="utf-8")
    if args.report:
        from truckd.ident.report import write_report

        index = write_report(diag, args.report, name)
        print(f"report: {index}")
    b, x = diag.baseline, diag.extended
    print(f"{diag.samples} samples in {diag.runs} run(s) ({diag.input} input)")
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
    ff = x.feedforward
    if ff is not None:
        print(
            f"feedforward (SysId form): kS={ff['kS']:.4g} V, kV={ff['kV']:.4g} V s/m, "
            f"kA={ff['kA']:.4g} V s^2/m"
        )
    return 0
