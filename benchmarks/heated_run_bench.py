"""One free run of the fast simulator with a resistance drift, beside backlash: its time.

A 10 000-sample plant log (100 Hz) with backlash (0.4 rad, 30 % of the inertia on the
rotor) and a winding that heats a little (``resistance_drift`` 3 K/W) or a lot (20 K/W,
time constant 5 s); :func:`truckd.ident.fastsim.simulate_voltage` on its input, median
of ``--runs``.  The kernel steps the heating in one run; without it (or with a kernel
that does not step it beside a gap) the run is repeated until the heating converges.
Run it in two trees to compare (``PYTHONPATH=TREE python -P TREE/benchmarks/...``).

    .venv/bin/python benchmarks/heated_run_bench.py [--runs N] [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import statistics
import time

import lab_path  # noqa: F401 - tests/ on sys.path, for labkit
from labkit.synth import plant_log
from results import machine, write_json

from truckd.config.truck import load_config
from truckd.ident import ckernel, fastsim
from truckd.model.effects import Effects

CASES = {
    "backlash_drift_3_k_per_w": 3.0,
    "backlash_drift_20_k_per_w": 20.0,
}
"""Each case's ``resistance_drift`` (K/W)."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=7, help="runs per case (median)")
    ap.add_argument("--json", metavar="FILE", help="write the results as JSON")
    ap.add_argument("--key", help="with --json: store the run under this name (results.py)")
    args = ap.parse_args()
    p = load_config().vehicle
    result: dict[str, object] = {"machine": machine(), "kernel": ckernel.available()}
    for name, drift in CASES.items():
        eff = Effects(
            backlash=0.4,
            rotor_inertia_fraction=0.3,
            resistance_drift=drift,
            winding_time_constant=5.0,
        )
        log = plant_log(p, eff, seed=3, n=10_000)
        t, u = log.columns["t"], log.columns["u"]
        times = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            fastsim.simulate_voltage(p, eff, t, u, 0.1)
            times.append(time.perf_counter() - t0)
        result[name] = {"median_ms": 1e3 * statistics.median(times), "runs": args.runs}
        print(f"{name}: {1e3 * statistics.median(times):.1f} ms (median of {args.runs})")
    if args.json:
        write_json(args.json, result, args.key)


if __name__ == "__main__":
    main()
