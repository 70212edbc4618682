"""The MPC solve's work, counted in instructions (callgrind; repeatable on a busy machine):
per solve and per OSQP iteration, the compiled path against the Python path.

The QPs are those of ``truckd sim``'s stop-and-go scenario at horizon 40 (the controller
through the simulated firmware and the estimator, as ``mpc_bench.py`` records them).  A
child process solves them once and twice with one path (``MpcSolver(compiled=...)``); the
difference of the two instruction counts divided by the extra solves is the work per
solve (imports, recording and set-up cancel), and divided by the extra iterations the work
per iteration.  The paths give the same iterations (tests/test_mpc_compiled.py).

    .venv/bin/python benchmarks/mpc_work.py [--cycles 600] [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from callgrind import counted
from results import machine, write_json

ROOT = Path(__file__).resolve().parent.parent

CHILD = r"""
import dataclasses, json, sys
sys.path.insert(0, sys.argv[1])
from mpc_bench import record_sim_sequence
from truckd.config.truck import load_config
from truckd.control.mpc import MpcSolver
from truckd.control.qp import ControlModel
compiled, cycles, reps = sys.argv[2] == "1", int(sys.argv[3]), int(sys.argv[4])
tc = load_config()
cfg = dataclasses.replace(tc.control, horizon=40, time_budget_s=float("inf"))
seq = record_sim_sequence(tc, cfg, cycles)
solvers = [MpcSolver(ControlModel(tc.vehicle), cfg, compiled=compiled) for _ in range(2)]
iters = 0
for s in solvers[:reps]:
    for mode, inp in seq:
        iters += s.solve(mode, inp).iterations
print(json.dumps({"solves": len(seq), "iterations": iters, "backend": solvers[0].backend}))
"""


def _count(compiled: bool, cycles: int, reps: int) -> tuple[dict[str, Any], int]:
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "child.py"
        script.write_text(CHILD)
        cmd = [sys.executable, str(script), str(ROOT / "benchmarks"), "1" if compiled else "0",
               str(cycles), str(reps)]  # fmt: skip
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
        proc, instructions = counted(cmd, env)
        return json.loads(proc.stdout.splitlines()[-1]), instructions


def run(cycles: int) -> dict[str, Any]:
    result: dict[str, Any] = {"qps": "stop-and-go, horizon 40", "cycles": cycles}
    for name, compiled in (("compiled", True), ("python", False)):
        one, i1 = _count(compiled, cycles, 1)
        two, i2 = _count(compiled, cycles, 2)
        extra_iters = two["iterations"] - one["iterations"]
        result[name] = {
            "backend": one["backend"],
            "instructions_per_solve": round((i2 - i1) / one["solves"]),
            "iterations_per_solve": extra_iters / one["solves"],
            "instructions_per_iteration": round((i2 - i1) / extra_iters),
        }
    result["machine"] = machine()
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cycles", type=int, default=600, help="QPs of the sequence")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--key", metavar="NAME", help="store the run under NAME (what_YYYY-MM-DD)")
    args = ap.parse_args()
    if shutil.which("valgrind") is None:
        print("mpc_work: valgrind not found", file=sys.stderr)
        return 2
    if not 10 <= args.cycles <= 100_000:
        print("mpc_work: --cycles must be in [10, 100000]", file=sys.stderr)
        return 2
    r = run(args.cycles)
    for name in ("compiled", "python"):
        x = r[name]
        print(f"mpc_work {name:8}: {x['instructions_per_solve']} instructions per solve, "
              f"{x['iterations_per_solve']:.1f} iterations, {x['instructions_per_iteration']} "
              f"per iteration ({x['backend']})")  # fmt: skip
    print(f"  load average {r['machine']['loadavg_1_5_15'][0]:.2f}")
    if args.json:
        write_json(args.json, r, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
