"""OSQP's settings for the move-blocked MPC QP: iterations per solve over many trucks and
scenarios, the shipped settings against a candidate, on the same QPs.

The QP sequences are recorded from ``truckd sim``'s six scenarios (the controller through
the simulated firmware, the protocol and the estimator, as on the car), each on a set of
trucks drawn around the configured one: inertia, mass, motor constant and resistance
scaled (:data:`TRUCKS`).  Each variant then solves every sequence from a fresh, warm-started
solver (the Python path: the same iterations as the compiled one, whose settings come from
:func:`truckd.control.mpc.osqp_settings` at start-up).  Reported per variant: iterations
mean, p50, p90, p99, p99.9 and max over all QPs, the worst sequence's mean, the largest
first-move difference (V) from an eps 1e-9 solve of the same QP sequence, and the solves
that ended without a usable solution; then the iterations on the recorded follow replay
(``tests/data/replay``, the sequence ``cycle_work.py`` counts instructions on) and the
largest spacing-error ratio (l2) of ten drawn trucks on lossy links braking
(``tests/test_sim_platoon_fleet.py``'s platoon, seed 5), also at the exact optimum (eps
1e-9).  Iterations do not depend on the machine; nothing here has a time budget
(simulated time).

    .venv/bin/python benchmarks/mpc_settings.py [--seconds 15] [--json FILE [--key NAME]]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
import sys
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
from results import machine, write_json

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import truckd.control.mpc as mpc  # noqa: E402
from truckd.config.truck import TruckConfig, load_config  # noqa: E402
from truckd.control.config import ControlConfig  # noqa: E402
from truckd.control.qp import ControlModel, QpInputs  # noqa: E402
from truckd.model.params import VehicleParams  # noqa: E402
from truckd.sim.closed_loop import SimSetup, run_scenario  # noqa: E402
from truckd.sim.scenarios import SCENARIO_NAMES, make_scenario  # noqa: E402

TRUCKS: dict[str, dict[str, float]] = {
    "configured": {},
    "mass x3": {"m": 3.0},
    "mass x0.5": {"m": 0.5},
    "motor constant x2": {"K_v": 2.0, "K_T": 2.0},
    "motor constant x0.5": {"K_v": 0.5, "K_T": 0.5},
    "inertia x0.3": {"J_S": 0.3},
    "inertia x3": {"J_S": 3.0},
    "resistance x2": {"R_m": 2.0},
    "mass x2, motor constant x1.5": {"m": 2.0, "K_v": 1.5, "K_T": 1.5},
    "mass x0.7, resistance x0.6": {"m": 0.7, "R_m": 0.6},
}
"""Trucks as factors on the configured truck's parameters."""

CANDIDATE = {"rho": 0.03, "alpha": 1.8, "adaptive_rho_tolerance": 5.0}
"""Settings measured against the shipped ones (:data:`truckd.control.mpc.RHO_BLOCKED`)."""

EXACT = {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 200_000, "time_limit": 10.0}
"""A solve to the optimum (the reference of the first moves and of the platoon)."""

REPLAY = ROOT / "tests" / "data" / "replay" / "run.rx.jsonl"

Sequence = list[tuple[str, QpInputs]]


def truck(base: VehicleParams, factors: dict[str, float]) -> VehicleParams:
    return dataclasses.replace(base, **{k: getattr(base, k) * f for k, f in factors.items()})


def record(tc: TruckConfig, p: VehicleParams, scenario: str, seconds: float) -> Sequence:
    """The QPs the controller solves in ``scenario`` on truck ``p``."""
    seq: Sequence = []
    inner = mpc.MpcSolver.solve

    def recording(
        self: mpc.MpcSolver, mode: str, inp: QpInputs, warm: bool = True
    ) -> mpc.MpcResult:
        seq.append((mode, inp))
        return inner(self, mode, inp, warm)

    cfg = tc.control.in_simulated_time()
    setup = SimSetup(p, tc.plant, cfg, ControlModel(p), tc.link.encoder_ticks_per_rev)
    with (
        mock.patch.object(mpc.MpcSolver, "solve", recording),
        mock.patch("truckd.control.controller.cnumerics.bind", return_value=(None, "recording")),
    ):
        run_scenario(make_scenario(scenario, p, cfg), setup, seconds)
    return seq


def shipped_with(over: dict[str, Any]) -> Any:
    """:func:`truckd.control.mpc.osqp_settings` with ``over`` on top for the move-blocked
    QP (patch it in for a run)."""
    shipped = mpc.osqp_settings
    return mock.patch.object(
        mpc, "osqp_settings", lambda c: {**shipped(c), **(over if c.move_blocks else {})}
    )


def replay_iterations(over: dict[str, Any]) -> float:
    """Mean OSQP iterations a solve on the recorded follow replay."""
    from truckd.runtime.replay import cycle_from_params
    from truckd.runtime.rxlog import read_rx_log

    with shipped_with(over):
        t0, params, cycles = read_rx_log(REPLAY)
        cyc = cycle_from_params(params, t0, str(REPLAY))
        outs = [cyc.step(inp).control for inp in cycles]
        iters = [c.solve_iterations for c in outs if c is not None and c.solve_iterations > 0]
    return round(sum(iters) / len(iters), 2)


def fleet_ratio(over: dict[str, Any]) -> float:
    """The largest spacing-error ratio (l2) of the drawn ten-truck platoon braking on
    lossy links (seed 5, as ``tests/test_sim_platoon_fleet.py``)."""
    from truckd.sim.platoon import make_platoon_scenario, run_platoon

    tc = load_config()
    setup = SimSetup(tc.vehicle, tc.plant, tc.control, ControlModel(tc.vehicle), 512)
    pcfg = dataclasses.replace(tc.platoon, plan_timeout_s=0.15)
    with shipped_with(over):
        sc = make_platoon_scenario("platoon-brake")
        m, _ = run_platoon(
            sc, setup, pcfg, 10, mixed=True, seed=5, loss=0.3, delay_s=(0.0, 0.05),
            clock_offset_s=2.0, clock_drift_ppm=100.0,
        )  # fmt: skip
    return round(float(max(m["string_ratio_l2"])), 4)


def solve_all(
    p: VehicleParams, cfg: ControlConfig, seq: Sequence, over: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray]:
    """Iterations and first moves (V, NaN where unusable) of ``seq`` solved with the
    settings ``over`` on top of the shipped ones."""
    with shipped_with(over):
        s = mpc.MpcSolver(ControlModel(p), cfg, compiled=False)
    iters, u0 = [], []
    for mode, inp in seq:
        r = s.solve(mode, inp)
        iters.append(r.iterations)
        u0.append(r.u0 if r.ok else math.nan)
    return np.array(iters), np.array(u0)


def run(seconds: float, variants: dict[str, dict[str, Any]]) -> dict[str, Any]:
    tc = load_config()
    cfg = tc.control.in_simulated_time()  # iterations, not the clock
    cases = []
    for name, factors in TRUCKS.items():
        p = truck(tc.vehicle, factors)
        for sc in SCENARIO_NAMES:
            seq = record(tc, p, sc, seconds)
            cases.append((name, sc, p, seq, solve_all(p, cfg, seq, EXACT)[1]))
            print(f"recorded {name}, {sc}: {len(seq)} QPs", file=sys.stderr)
    out: dict[str, Any] = {
        "what": __doc__.split("\n\n")[0].replace("\n", " "),
        "date": datetime.date.today().isoformat(),
        "trucks": TRUCKS,
        "scenarios": list(SCENARIO_NAMES),
        "seconds_per_scenario": seconds,
        "qps": sum(len(c[3]) for c in cases),
        "variants": {},
    }
    for vname, over in variants.items():
        its, means, du, fails = [], [], 0.0, 0
        for _name, _sc, p, seq, ref in cases:
            it, u = solve_all(p, cfg, seq, over)
            its.append(it)
            means.append(float(it.mean()))
            ok = ~np.isnan(u)
            du = max(du, float(np.max(np.abs(u[ok] - ref[ok]))) if ok.any() else du)
            fails += int((~ok).sum())
        a = np.concatenate(its)
        row = {
            "settings": {**{k: mpc.osqp_settings(cfg)[k] for k in CANDIDATE}, **over},
            "iterations_mean": round(float(a.mean()), 2),
            "iterations_p50": float(np.percentile(a, 50)),
            "iterations_p90": float(np.percentile(a, 90)),
            "iterations_p99": float(np.percentile(a, 99)),
            "iterations_p999": float(np.percentile(a, 99.9)),
            "iterations_max": int(a.max()),
            "worst_sequence_mean": round(max(means), 2),
            "max_abs_du0_vs_exact_v": du,
            "unusable_solves": fails,
            "replay_iterations_mean": replay_iterations(over),
            "fleet_brake_seed5_string_ratio_l2_max": fleet_ratio(over),
        }
        out["variants"][vname] = row
        print(f"{vname}: {row}", file=sys.stderr)
    out["fleet_brake_seed5_string_ratio_l2_max_exact"] = fleet_ratio(EXACT)
    out["machine"] = machine()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=15.0, help="simulated s per scenario")
    ap.add_argument("--json", metavar="FILE")
    ap.add_argument("--key", help="store the run under this name (what_YYYY-MM-DD)")
    args = ap.parse_args()
    result = run(args.seconds, {"shipped": {}, "candidate": CANDIDATE})
    if args.json:
        write_json(args.json, result, args.key)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
