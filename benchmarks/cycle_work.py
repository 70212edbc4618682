"""The companion step's work per cycle, counted in instructions (repeatable on a noisy
machine) and timed hot (back to back) and paced (one cycle per 10 ms, as on the car).

The step is the pure part of every cycle: sensors -> controller (the MPC solve) ->
supervisor -> motor command, then the plan, the state message and the log row, on the
inputs of the stored daemon run ``tests/data/replay/run.rx.jsonl`` (300 cycles of follow
at 100 Hz; the same inputs every time).  Poll, send and publish are I/O and are measured
by ``loop_bench.py``.

* ``instructions_per_cycle``: ``valgrind --tool=callgrind`` counts the instructions of the
  whole process replaying the log once and three times; the difference divided by the
  extra cycles is the step's own count (imports and set-up, the same in both, cancel).
  The same code and inputs give about the same count whatever the machine is doing
  (OpenBLAS held to one thread).
* ``cold_lines_per_cycle``: ``valgrind --tool=cachegrind`` with its cache simulation
  (32 kB L1s, a 2 MB last level) while a 4 MB array is written between the steps, so each
  step starts with cold caches, as after the loop's sleep: the 64-byte lines of code
  (``code``) and data (``data``, reads and writes) the step fetches from memory, the
  same with and without the steps subtracted.  The cycle's time after the sleep goes
  mostly into these fetches; unlike a time, the count repeats on a busy machine.
* ``osqp_iterations``: the MPC's OSQP iterations per solve over the replay's cycles that
  solved (mean, p99, how many);
* ``hot_us_p50``: wall time per step back to back (caches warm);
  ``paced_us_p50``: the same with a 10 ms sleep after each step: the caches and the
  branch predictors go cold in the sleep, as they do in the daemon's loop, and each numpy
  or OSQP call then costs several times its hot time.
* ``busy_gap_us_p50``: the same with the gap spent busy instead of asleep (1, 3, 10 ms
  of a Python loop that reads the clock and touches none of the step's memory).  Where
  the step's cost grows with the gap although nothing in the process evicted its lines,
  something outside the process does: on a virtual machine, the host's other tenants
  and the host moving the virtual CPU between cores.  This machine: see README.

``--root DIR`` measures the truckd of another checkout (e.g. an earlier commit's git archive, for a
side-by-side figure).

    .venv/bin/python benchmarks/cycle_work.py [--root DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from callgrind import counted
from results import machine, write_json

ROOT = Path(__file__).resolve().parent.parent
LOG = ROOT / "tests" / "data" / "replay" / "run.rx.jsonl"

STEP = r"""
import sys
sys.path.insert(0, sys.argv[1])
from truckd.runtime.rxlog import read_rx_log
from truckd.runtime.replay import cycle_from_params
from truckd.runtime.platoon_link import cycle_plan
def step(cyc, inp):  # the cycle's pure work: step, plan, state message, log row
    out = cyc.step(inp)
    plan = cycle_plan(cyc, out, 0.0, "truck1")
    if plan is not None:
        plan.as_dict()
    cyc.state_message(out)
    cyc.log_row(out)
    return out
"""  # the step both replays run: each child script starts with it

CHILD = (
    STEP
    + r"""
import json, time
path, reps, pace, spin = sys.argv[2], int(sys.argv[3]), float(sys.argv[4]), sys.argv[5] == "1"
t0, params, cycles = read_rx_log(path)
cycles = list(cycles)
cycs = [cycle_from_params(params, t0, path) for _ in range(3)]  # set-up alike for any reps
times = []
iterations = []
pc = time.perf_counter
for cyc in cycs[:reps]:
    for inp in cycles:
        a = pc()
        out = step(cyc, inp)
        times.append(pc() - a)
        iterations.append(out.control.solve_iterations)
        if pace > 0.0 and spin:  # busy, touching nothing of the step's
            end = pc() + pace
            while pc() < end:
                pass
        elif pace > 0.0:
            time.sleep(pace)
print(json.dumps({"cycles": len(cycles), "times": times, "iterations": iterations}))
"""
)

COLD_CHILD = (
    STEP
    + r"""
import numpy as np
path, k, steps = sys.argv[2], int(sys.argv[3]), sys.argv[4] == "1"
t0, params, cycles = read_rx_log(path)
cycles = list(cycles)
cyc = cycle_from_params(params, t0, path)
sweep = np.zeros(4 * 1024 * 1024 // 8)  # twice the simulated last level
for inp in cycles[:50]:  # warm start, as in the loop
    step(cyc, inp)
for inp in cycles[50 : 50 + k]:
    sweep += 1.0
    if steps:
        step(cyc, inp)
"""
)
COLD_STEPS = 60
BUSY_GAPS_S = (0.001, 0.003, 0.01)
CACHES = ["--I1=32768,8,64", "--D1=32768,8,64", "--LL=2097152,16,64"]


def _cold_lines(root: Path) -> dict[str, int]:
    """Lines fetched from memory per step with cold caches (cachegrind, module doc)."""
    totals = []
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "cold.py"
        script.write_text(COLD_CHILD)
        for steps in ("1", "0"):
            out_file = Path(tmp) / f"cg.{steps}"
            cmd = ["valgrind", "--tool=cachegrind", "--cache-sim=yes", *CACHES,
                   f"--cachegrind-out-file={out_file}", sys.executable, str(script),
                   str(root), str(LOG), str(COLD_STEPS), steps]  # fmt: skip
            env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"cold replay failed: {proc.stderr[-2000:]}")
            events: list[str] = []
            summary: list[int] = []
            for line in out_file.read_text().splitlines():
                if line.startswith("events:"):
                    events = line.split()[1:]
                elif line.startswith("summary:"):
                    summary = [int(x) for x in line.split()[1:]]
            totals.append(dict(zip(events, summary, strict=True)))
    d = {e: (totals[0][e] - totals[1][e]) / COLD_STEPS for e in totals[0]}
    return {"code": round(d["ILmr"]), "data": round(d["DLmr"] + d["DLmw"])}


def _child(
    root: Path, reps: int, pace: float, valgrind: bool, spin: bool = False
) -> tuple[dict[str, Any], int]:
    """Run the replay in a fresh process; (its JSON, instructions or 0).  ``pace`` s
    between steps, asleep or (``spin``) busy in a loop that touches none of the step's
    memory."""
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "child.py"
        script.write_text(CHILD)
        cmd = [sys.executable, str(script), str(root), str(LOG), str(reps), str(pace),
               "1" if spin else "0"]  # fmt: skip
        env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
        instructions = 0
        if valgrind:
            proc, instructions = counted(cmd, env, "replay")
        else:
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
            if proc.returncode != 0:
                raise RuntimeError(f"replay failed: {proc.stderr[-2000:]}")
        return json.loads(proc.stdout.splitlines()[-1]), instructions


def _p50_us(times: list[float]) -> float:
    xs = sorted(times[10:])  # the first cycles start the solver cold
    return xs[len(xs) // 2] * 1e6


def run(root: Path) -> dict[str, Any]:
    result: dict[str, Any] = {"root": str(root), "log": str(LOG.relative_to(ROOT))}
    if shutil.which("valgrind"):
        one, i1 = _child(root, 1, 0.0, True)
        _, i3 = _child(root, 3, 0.0, True)
        result["instructions_per_cycle"] = round((i3 - i1) / (2 * one["cycles"]))
        result["cold_lines_per_cycle"] = _cold_lines(root)
    else:
        result["instructions_per_cycle"] = None
        result["cold_lines_per_cycle"] = None
        result["note"] = "valgrind not found: no instruction count"
    hot, _ = _child(root, 3, 0.0, False)
    paced, _ = _child(root, 1, 0.01, False)
    result["cycles"] = hot["cycles"]
    solved = [n for n in hot["iterations"][: hot["cycles"]] if n > 0]
    result["osqp_iterations"] = {
        "mean": round(sum(solved) / len(solved), 2) if solved else None,
        "p99": sorted(solved)[int(0.99 * (len(solved) - 1))] if solved else None,
        "solves": len(solved),
    }
    result["hot_us_p50"] = _p50_us(hot["times"])
    result["paced_us_p50"] = _p50_us(paced["times"])
    result["busy_gap_us_p50"] = {
        f"{gap * 1e3:g} ms": _p50_us(_child(root, 1, gap, False, spin=True)[0]["times"])
        for gap in BUSY_GAPS_S
    }
    result["machine"] = machine()
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=ROOT, help="the checkout whose truckd runs")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument(
        "--key",
        metavar="NAME",
        help="store the run under NAME in --json's file (what_YYYY-MM-DD), not at its top level",
    )
    args = ap.parse_args()
    if not (args.root / "truckd" / "runtime" / "cycle.py").is_file():
        print(f"cycle_work: {args.root}: not a truckd checkout", file=sys.stderr)
        return 2
    r = run(args.root.resolve())
    ipc = r["instructions_per_cycle"]
    print(f"cycle_work: {r['cycles']} cycles of {r['log']} ({r['root']})")
    print(f"  instructions per cycle  {ipc if ipc is not None else 'n/a (no valgrind)'}")
    cold = r["cold_lines_per_cycle"]
    if cold is not None:
        print(f"  cold lines per cycle    code {cold['code']}, data {cold['data']} (64 B each)")
    print(f"  hot p50 / paced p50     {r['hot_us_p50']:.0f} / {r['paced_us_p50']:.0f} us")
    busy = ", ".join(f"{k} {v:.0f}" for k, v in r["busy_gap_us_p50"].items())
    print(f"  p50 after a busy gap    {busy} us")
    print(f"  load average            {r['machine']['loadavg_1_5_15'][0]:.2f}")
    if args.json:
        write_json(args.json, r, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
