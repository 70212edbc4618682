"""Real logs: truckd's validation fit beside the data's own least squares (WPILib SysId's).

Each argument is one case: ``FIT[,FIT...]=VALIDATE[,VALIDATE...]`` (logs or SysId
``FILE.json:test,...`` selectors), or a bare SysId ``FILE.json``, fitted on its
quasistatic ramps and validated on its dynamic steps, as SysId users validate.  Each case
is diagnosed against the default configuration (a prior: the data decide the machine).
Reported per case: samples, least-squares fit, seed and extended fit (free run on the
validation logs), causes named, unexplained, the notes a user must see, and the time.
The logs are not part of the repository: give their paths (and quote their source).

    .venv/bin/python benchmarks/diagnose_real.py CASE [CASE ...] [--jobs N]
        [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from typing import Any

from results import write_json

from truckd.config.truck import load_config
from truckd.errors import InputError
from truckd.ident import ckernel
from truckd.ident.api import diagnose_log, read_logs

RAMPS = ("slow-forward", "slow-backward")
STEPS = ("fast-forward", "fast-backward")


def _split(case: str) -> tuple[list[str], list[str]]:
    if "=" in case:
        fit, val = case.split("=", 1)
        return fit.split("+"), val.split("+")
    return [f"{case}:{','.join(RAMPS)}"], [f"{case}:{','.join(STEPS)}"]


def _one(case: str, jobs: int = 1) -> dict[str, Any]:
    fit, val = _split(case)
    p = load_config().vehicle
    logs, vals = read_logs(fit), read_logs(val)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    d = diagnose_log(logs, p, vals, workers=jobs)
    secs = time.perf_counter() - t0
    ls = d.least_squares or {}
    return {
        "case": case,
        "samples": d.samples + sum(len(v.columns["t"]) for v in vals),
        "least_squares_fit_percent": ls.get("fit_percent"),
        "least_squares": ls,
        "seed_fit_percent": d.baseline.fit_percent,
        "extended_fit_percent": d.extended.fit_percent,
        "gain_over_least_squares": (
            d.extended.fit_percent - ls["fit_percent"] if ls.get("fit_percent") else None
        ),
        "effects": [f.name for f in d.effects],
        "unexplained": d.unexplained,
        "alerts": d.alerts,
        "seconds": secs,
        "jobs": jobs,
        "loadavg_1min": round(load, 2),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="FIT=VALIDATE or a SysId FILE.json")
    ap.add_argument("--json", metavar="FILE", help="write the rows as JSON")
    ap.add_argument("--key", help="with --json: store the run under this name (results.py)")
    ap.add_argument(
        "--jobs", type=int, default=1, help="worker processes of each diagnosis (default 1)"
    )
    args = ap.parse_args()
    rows = []
    for case in args.cases:
        try:
            r = _one(case, args.jobs)
        except InputError as exc:  # a log the diagnosis refuses: its row says why
            print(f"{case}: refused: {exc}")
            rows.append({"case": case, "refused": str(exc)})
            continue
        rows.append(r)
        ls = r["least_squares_fit_percent"]
        print(
            f"{case}: least squares {ls:.1f} %  truckd {r['extended_fit_percent']:.1f} % "
            f"(seed {r['seed_fit_percent']:.1f} %)  {r['effects']}  "
            f"unexplained={r['unexplained']}  {r['seconds']:.1f} s (load {r['loadavg_1min']})"
            if ls is not None
            else f"{case}: no least-squares model; truckd {r['extended_fit_percent']:.1f} %"
        )
        for a in r["alerts"]:
            print(f"    {a}")
    machine = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "c_kernel": ckernel.available(),
    }
    if args.json:
        write_json(args.json, {"machine": machine, "rows": rows}, args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())
