"""Simulated-plant speed: a 60 s log at 100 Hz, open loop, on one core.

Prints a table and, with ``--json FILE``, writes ``{date, machine, results}`` (the
machine with its load; ``--key NAME``: under that key, the file's other measurements kept,
see ``results.py``).  Aim: at least 1000x faster than real time, i.e. under 60 ms of
compute for the 60 s log.
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import time

import numpy as np
from results import machine, write_json

from truckd.config.truck import load_config
from truckd.model.effects import Effects
from truckd.sim.plant import PlantConfig, simulate_open_loop

CASES = {
    "seed model": PlantConfig(),
    "all effects + noise + encoder": PlantConfig(
        effects=Effects(
            viscous_friction=1e-6,
            aero_drag=0.5,
            load_force=1.0,
            load_force_amplitude=0.5,
            input_delay=0.025,
            dead_zone=0.3,
            voltage_saturation=6.5,
            battery_sag=0.05,
            sensor_lag=0.03,
        ),
        noise_v=0.01,
        noise_i=0.1,
        encoder_ticks_per_rev=360,
        seed=1,
    ),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", help="write results here")
    ap.add_argument("--key", help="store the run under this name (what_YYYY-MM-DD)")
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    p = load_config().vehicle
    t = np.arange(0.0, 60.0, 0.01)
    rng = np.random.default_rng(0)
    u = np.clip(rng.uniform(-6, 6, 60).repeat(100) + 1.5 * np.sin(2 * np.pi * 0.5 * t), -7, 7)
    rows = []
    for name, cfg in CASES.items():
        times = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            simulate_open_loop(p, t, u, cfg)
            times.append(time.perf_counter() - t0)
        med = statistics.median(times)
        rows.append(
            {
                "case": name,
                "samples": len(t),
                "sim_seconds": 60.0,
                "compute_ms_median": med * 1e3,
                "compute_ms_min": min(times) * 1e3,
                "x_realtime": 60.0 / med,
            }
        )
    print(f"{'case':<32}{'median ms':>10}{'min ms':>9}{'x real time':>13}")
    for r in rows:
        print(
            f"{r['case']:<32}{r['compute_ms_median']:>10.1f}{r['compute_ms_min']:>9.1f}"
            f"{r['x_realtime']:>13.0f}"
        )
    if args.json:
        date = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d")
        write_json(args.json, {"date": date, "machine": machine(), "results": rows}, args.key)


if __name__ == "__main__":
    main()
