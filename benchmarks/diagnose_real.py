"""Real logs: truckd's validation fit beside the data's own least squares (WPILib SysId's).

Each argument is one case: ``FIT[+FIT...]=VALIDATE[+VALIDATE...]`` (logs or SysId
``FILE.json:test,...`` selectors), or a bare SysId ``FILE.json``, split by ``--split``:
``ramps-steps`` (default) fits its quasistatic ramps and validates on its dynamic steps,
as SysId users validate (the steps' accelerations, supply and current limits are then
unseen in the fit); ``directions`` fits the forward ramp and step and validates on the
backward ones (both halves hold every kind of motion); ``whole`` fits the whole file and
validates as ``truckd diagnose FILE.json`` does by default (the last 30 % of each run,
what a user who gives no ``--validate`` sees).  Each case is diagnosed against
the default configuration (a prior: the data decide the machine).  Reported per case:
samples, least-squares fit, seed and extended fit (free run on the validation logs), the
noise ceiling (the fit a model leaving only the speed's measurement noise reaches),
whether the goal (fit at least 90 %, and least squares + 5 points where it is below
95 %) is met and whether the ceiling leaves room for it, causes named, unexplained, the
notes a user must see, and the time.  The logs are not part of the repository: give
their paths (and quote their source).

    .venv/bin/python benchmarks/diagnose_real.py CASE [CASE ...] [--jobs N]
        [--split ramps-steps|directions|whole] [--json FILE [--key NAME]]
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

SPLITS = {
    "ramps-steps": (("slow-forward", "slow-backward"), ("fast-forward", "fast-backward")),
    "directions": (("slow-forward", "fast-forward"), ("slow-backward", "fast-backward")),
}
"""How a bare SysId file is split: (fitted tests, validation tests); ``whole`` (not
here) gives the whole file and the command's own validation."""

GOAL_FIT = 90.0
GOAL_OVER_LS = 5.0
GOAL_LS_HIGH = 95.0


def _split(case: str, split: str) -> tuple[list[str], list[str]]:
    if "=" in case:
        fit, val = case.split("=", 1)
        return fit.split("+"), val.split("+")
    if split == "whole":
        return [case], []
    fit_tests, val_tests = SPLITS[split]
    return [f"{case}:{','.join(fit_tests)}"], [f"{case}:{','.join(val_tests)}"]


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f} %"


def goal(ls: float | None) -> float:
    """The validation fit the goal asks for: 90 %, and least squares + 5 points where
    least squares is below 95 % (at least least squares where it is above)."""
    if ls is None:
        return GOAL_FIT
    return max(GOAL_FIT, ls + GOAL_OVER_LS if ls < GOAL_LS_HIGH else ls)


def _one(case: str, split: str, jobs: int = 1) -> dict[str, Any]:
    fit, val = _split(case, split)
    p = load_config().vehicle
    logs, vals = read_logs(fit), (read_logs(val) if val else [])
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    d = diagnose_log(logs, p, vals, workers=jobs)
    secs = time.perf_counter() - t0
    ls = d.least_squares or {}
    want = goal(ls.get("fit_percent"))
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
        "fit_ceiling_percent": d.fit_ceiling,
        "goal_fit_percent": want,
        "goal_met": d.extended.fit_percent >= want,
        "goal_below_ceiling": (None if d.fit_ceiling is None else want <= d.fit_ceiling),
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
    ap.add_argument(
        "--split",
        choices=[*sorted(SPLITS), "whole"],
        default="ramps-steps",
        help="how a bare SysId FILE.json is split into fit and validation (default ramps-steps)",
    )
    args = ap.parse_args()
    rows = []
    for case in args.cases:
        try:
            r = _one(case, args.split, args.jobs)
        except InputError as exc:  # a log the diagnosis refuses: its row says why
            print(f"{case}: refused: {exc}")
            rows.append({"case": case, "refused": str(exc)})
            continue
        rows.append(r)
        ls = r["least_squares_fit_percent"]
        print(
            f"{case}: least squares {ls:.1f} %  truckd {r['extended_fit_percent']:.1f} % "
            f"(seed {r['seed_fit_percent']:.1f} %, ceiling {_pct(r['fit_ceiling_percent'])}, "
            f"goal {r['goal_fit_percent']:.1f} %: {'met' if r['goal_met'] else 'missed'})  "
            f"{r['effects']}  "
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
        write_json(args.json, {"machine": machine, "split": args.split, "rows": rows}, args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())
