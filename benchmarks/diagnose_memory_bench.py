"""Peak memory and time of ``truckd diagnose`` on long logs (a child process per log).

A synthetic log of ``--rows`` rows at 100 Hz (``t, u, v``: piecewise-constant voltage
levels of 2 s, a first-order truck with 0.6 s time constant, 3 mm/s speed noise; the
same text per row as a daemon-style export, about 22 bytes) is written to a temporary
directory; ``truckd diagnose LOG`` runs in a child process, whose peak resident memory
(``getrusage(RUSAGE_CHILDREN).ru_maxrss`` in a process of its own per log), CPU time and
wall time are recorded.  CPU
time is the figure to compare on a shared machine (wall time includes waiting for it).

    nice .venv/bin/python benchmarks/diagnose_memory_bench.py [--rows N ...]
        [--json FILE] [--key NAME]

Results are merged into the JSON file under ``--key`` (default
``diagnose_memory_<UTC date>``), with the date, the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.signal import lfilter

ROOT = Path(__file__).resolve().parent.parent


def write_log(path: Path, rows: int, seed: int = 1) -> int:
    """The synthetic log (see module docstring); returns its size in bytes."""
    rng = np.random.default_rng(seed)
    dt = 0.01
    levels = rng.uniform(-2.0, 6.0, size=rows // 200 + 2)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("t,u,v\n")
        state = np.zeros(1)
        a = float(np.exp(-dt / 0.6))
        step = 500_000
        for k in range(0, rows, step):
            n = min(step, rows - k)
            idx = np.arange(k, k + n)
            u = levels[idx // 200]
            v, state = lfilter([0.25 * (1 - a)], [1.0, -a], u, zi=state)
            v = v + rng.normal(0.0, 0.003, n)
            np.savetxt(fh, np.column_stack([idx * dt, u, v]), fmt=["%.2f", "%.3f", "%.5f"],
                       delimiter=",")  # fmt: skip
    return path.stat().st_size


_CHILD = """
import json, resource, subprocess, sys, time
t0 = time.perf_counter()
p = subprocess.run(sys.argv[1:], capture_output=True, text=True, check=False)
wall = time.perf_counter() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps({"code": p.returncode, "stdout": p.stdout, "stderr": p.stderr, "wall": wall,
                  "maxrss_kib": ru.ru_maxrss, "cpu": ru.ru_utime + ru.ru_stime}))
"""
"""Runs the command as its only child and reports that child's rusage (ru_maxrss of
RUSAGE_CHILDREN is the largest child so far: one measuring process per log)."""


def measure(log: Path) -> dict[str, Any]:
    """``truckd diagnose log`` in a child: peak RSS (MiB), CPU and wall seconds."""
    cmd = [sys.executable, "-m", "truckd.cli.main", "diagnose", str(log)]
    p = subprocess.run(
        [sys.executable, "-c", _CHILD, *cmd], cwd=ROOT, capture_output=True, text=True, check=True
    )
    r = json.loads(p.stdout)
    if r["code"] != 0:
        raise SystemExit(f"diagnose failed ({r['code']}): {r['stderr'][-2000:]}")
    return {
        "peak_rss_mib": r["maxrss_kib"] / 1024.0,  # KiB on Linux
        "cpu_s": r["cpu"],
        "wall_s": r["wall"],
        "notes": [ln for ln in r["stderr"].splitlines() if ln.startswith("note:")],
        "fit_line": next((ln for ln in r["stdout"].splitlines() if ln.startswith("extended")), ""),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[3_000_000])
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "diagnose_memory_bench.json"))
    ap.add_argument("--key", default=f"diagnose_memory_{time.strftime('%Y-%m-%d', time.gmtime())}")
    args = ap.parse_args()
    machine = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "loadavg_before": os.getloadavg(),
    }
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for rows in sorted(args.rows):
            log = Path(tmp) / f"log{rows}.csv"
            size = write_log(log, rows)
            r = {"rows": rows, "log_bytes": size, **measure(log)}
            r["peak_bytes_per_row"] = r["peak_rss_mib"] * 1024 * 1024 / rows
            print(json.dumps(r), flush=True)
            runs.append(r)
            log.unlink()
    machine["loadavg_after"] = os.getloadavg()
    result = {"date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine,
              "runs": runs}  # fmt: skip
    path = Path(args.json)
    doc = json.loads(path.read_text()) if path.exists() else {}
    doc[args.key] = result
    path.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"-> {path} [{args.key}]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
