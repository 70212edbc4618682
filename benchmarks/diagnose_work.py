"""How much work one diagnosis is, counted rather than timed: free runs and instructions.

On a shared machine the wall time of ``truckd diagnose`` moves by 40 % from one hour to
the next; two counts do not. For each log: the free runs the diagnosis simulates (in
this process, one worker: ``truckd.ident.fastsim`` runs counted) and the instructions of
the whole command (``valgrind --tool=callgrind`` on ``python -m truckd diagnose LOG --jobs
1``: start-up, reading, every fit and the report; about 60 times slower than the command).
Run it on two trees side by side (``PYTHONPATH=OTHER_TREE python OTHER_TREE/benchmarks/...``
makes this script, and the command it counts, run the other tree's ``truckd``) to compare
code, not machines.

    nice .venv/bin/python benchmarks/diagnose_work.py [LOG ...] [--no-callgrind]
        [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from callgrind import counted
from results import machine, write_json

import truckd
from truckd.config.truck import load_config
from truckd.ident import ckernel, fastsim
from truckd.ident.api import diagnose_log, read_logs

SWERVE = Path(__file__).resolve().parents[1] / "tests" / "data" / "sysid" / "frc_swerve_12_12.json"
"""The real log a fresh clone has (WPILib SysId, an FRC swerve drivetrain)."""


def free_runs(path: str) -> dict[str, Any]:
    """The free runs one diagnosis of ``path`` simulates (one worker), and what it names."""
    count = {"runs": 0}
    simulate = fastsim._simulate

    def counted(*args: Any) -> Any:
        count["runs"] += 1
        return simulate(*args)

    fastsim._simulate = counted  # type: ignore[assignment]
    try:
        logs = read_logs([path])
        d = diagnose_log(logs, load_config().vehicle, workers=1)
    finally:
        fastsim._simulate = simulate  # type: ignore[assignment]
    return {
        "samples": sum(len(lg.columns["t"]) for lg in logs),
        "free_runs": count["runs"],
        "named": [f.name for f in d.effects],
        "extended_fit_percent": d.extended.fit_percent,
    }


def instructions(path: str) -> int | None:
    """Instructions of ``python -m truckd diagnose path --jobs 1`` under callgrind (None:
    no valgrind)."""
    if shutil.which("valgrind") is None:
        return None
    # The command runs this process's truckd: its tree first on the path, and no current
    # directory there (-P: run from another tree's top, -m would import that tree's).
    tree = str(Path(truckd.__file__).resolve().parents[1])
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, (tree, os.environ.get("PYTHONPATH")))),
    }
    cmd = [sys.executable, "-P", "-m", "truckd", "diagnose", path, "--jobs", "1"]
    return counted(cmd, env=env, what="diagnose")[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "logs",
        nargs="*",
        default=[str(SWERVE)],
        help="CSV or SysId JSON logs, each diagnosed whole (default: the swerve log the "
        "tests ship)",
    )
    ap.add_argument("--no-callgrind", action="store_true", help="count the free runs only")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    ap.add_argument("--key", help="with --json: store the run under this name (results.py)")
    args = ap.parse_args()
    rows = []
    for path in args.logs:
        t0 = time.monotonic()
        row: dict[str, Any] = {"log": path, **free_runs(path)}
        if not args.no_callgrind:
            row["instructions"] = instructions(path)
        row["seconds"] = round(time.monotonic() - t0, 1)
        rows.append(row)
        print(row, file=sys.stderr, flush=True)
    result = {
        "what": "free runs of one diagnosis (one worker) and instructions of the command "
        "(callgrind, --jobs 1), per log",
        "date": time.strftime("%Y-%m-%d"),
        "truckd": str(Path(truckd.__file__).parent),
        "c_kernel": ckernel.available(),
        "rows": rows,
        "machine": machine(),
    }
    if args.json:
        write_json(args.json, result, args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())
