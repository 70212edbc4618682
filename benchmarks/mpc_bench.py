"""MPC solve time: warm-started OSQP (the controller) vs a cold OSQP setup per cycle vs
cvxpy (CLARABEL) per cycle, on the same sequence of QPs, for horizons 20, 40, 80.

The controller is timed in both formulations back to back (replays alternating): the
move-blocked condensed QP (``blocked``, the default ``move_blocks``, 8 if the
configuration has 0) and the sparse QP (``sparse``, ``move_blocks: 0``).  Cold OSQP and
cvxpy solve the sparse QP (the full problem); ``max_abs_diff_u`` of ``blocked`` is thus
the first-move change that blocking makes against the full QP's optimum.  ``sparse_1e-5``
is the sparse QP at the tolerance it shipped with until 2026-11-23
(:data:`SPARSE_EPS_UNTIL_2026_11_23`).

What each time covers (wall clock, ``time.perf_counter`` around the call):

* warm: ``MpcSolver.solve`` whole, as the controller calls it every cycle: input check,
  building q/l/u, OSQP update, shifted warm start, solve, status and solution checks;
* cold: a new OSQP object set up on the same P, A, q, l, u and solved (the controller's
  settings without its time budget; building q/l/u is not timed);
* cvxpy: a parametrised cvxpy problem (built once per mode, so cvxpy's compilation is in
  the first cycle only, as a controller written with cvxpy would do it): setting the
  parameters q, l, u and ``Problem.solve(solver=CLARABEL)``, i.e. cvxpy's per-solve
  canonicalisation plus the interior-point solve, every cycle, no warm start (CLARABEL
  has none).

The QP sequence is recorded from ``truckd sim``'s stop-and-go scenario (the controller
through the simulated firmware, the protocol and the estimator, the plant with Coulomb
friction and stiction), so the warm start sees what it sees on the car: encoder
quantisation and range noise change the QP from cycle to cycle.  ``--sequence ideal``
records it from a loop on the true speed and gap instead (smoother: fewer iterations).
Each solver then replays the same sequence.  ``max_abs_diff_u`` is the largest
first-move difference (V) between the warm-started controller and cvxpy.

    .venv/bin/pip install -e '.[bench]'    # cvxpy, for the comparison (make bench does it)
    .venv/bin/python benchmarks/mpc_bench.py [--json FILE] [--cycles N] [--cvxpy-cycles M]
        [--sequence sim|ideal]
    .venv/bin/python benchmarks/mpc_bench.py --paths [--json FILE --key NAME]

``--paths`` times only the shipped blocked QP at N=40 with the compiled and the Python path
(:mod:`truckd.control.ccycle`) replayed alternately on the same sequence (wall clock and CPU
time per ``MpcSolver.solve``), and stores the run under ``--key`` in ``--json``'s file.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import os
import platform
import sys
import time
from typing import Any
from unittest import mock

import numpy as np
import osqp
import scipy.sparse as sp
from results import write_json

from truckd.config.truck import TruckConfig, load_config
from truckd.control.config import ControlConfig
from truckd.control.controller import Controller
from truckd.control.estimator import Estimate
from truckd.control.mpc import MpcResult, MpcSolver, osqp_settings
from truckd.control.qp import ControlModel, QpInputs
from truckd.sim.closed_loop import SimSetup, run_scenario
from truckd.sim.plant import Plant
from truckd.sim.scenarios import World, make_scenario

TICKS = load_config().ticks_per_rev

SPARSE_EPS_UNTIL_2026_11_23 = 1e-5
"""The OSQP tolerance the sparse QP shipped with until 2026-11-23 (``sparse_1e-5`` rows)."""

CVXPY_NOTE = (
    "warm: MpcSolver.solve whole (q/l/u, update, shifted warm start, solve, checks); "
    "cold: new OSQP setup + solve per QP; cvxpy: parametrised problem built once, each "
    "QP = set parameters + Problem.solve(CLARABEL) (canonicalisation + solve)"
)


def record_sim_sequence(
    tc: TruckConfig, cfg: ControlConfig, cycles: int
) -> list[tuple[str, QpInputs]]:
    """QPs the controller solves in ``truckd sim``'s stop-and-go scenario: through the
    simulated firmware, the protocol and the estimator (encoder quantisation, range noise),
    as on the car.  A budget no solve reaches, so the sequence does not depend on load."""
    seq: list[tuple[str, QpInputs]] = []
    inner = MpcSolver.solve

    def recording(self: MpcSolver, mode: str, inp: QpInputs, warm: bool = True) -> MpcResult:
        seq.append((mode, inp))
        return inner(self, mode, inp, warm)

    setup = SimSetup(
        tc.vehicle, tc.plant, cfg, ControlModel(tc.vehicle), tc.link.encoder_ticks_per_rev
    )
    # The controller's numerics in Python (cnumerics unbound): its MPC then solves through
    # MpcSolver.solve (compiled or not), where the inputs are recorded.
    with (
        mock.patch.object(MpcSolver, "solve", recording),
        mock.patch("truckd.control.controller.cnumerics.bind", return_value=(None, "recording")),
    ):
        run_scenario(make_scenario("stop-and-go", tc.vehicle, cfg), setup, cycles * cfg.period)
    return seq


def record_sequence(
    model: ControlModel, cfg: ControlConfig, cycles: int
) -> list[tuple[str, QpInputs]]:
    """QPs the controller solves in a closed-loop stop-and-go run with ideal estimates
    (the true speed and gap: smoother than on the car, so warm starts fare better)."""
    ctrl = Controller(model, cfg.in_simulated_time(), TICKS)
    seq: list[tuple[str, QpInputs]] = []
    inner = ctrl.mpc.solve

    def recording(mode: str, inp: QpInputs, warm: bool = True) -> Any:
        seq.append((mode, inp))
        return inner(mode, inp, warm)

    ctrl.mpc.solve = recording  # type: ignore[method-assign]
    sc = make_scenario("stop-and-go", model.params, cfg)
    world = World(sc)
    plant = Plant(model.params)
    plant.reset(v=sc.v0)
    for _ in range(cycles):
        t = plant.t
        gap = world.gap(t, plant.x)
        v_lead = world.v_lead(t)
        assert gap is not None and v_lead is not None
        est = Estimate(plant.v, True, gap, v_lead, True, "tracking", 0.01, 0, 0, 0, 0)
        out = ctrl.control(est)
        plant.command(out.u)
        plant.advance(cfg.period)
    return seq


@dataclasses.dataclass
class WarmRun:
    """One replay of the sequence by the warm-started controller."""

    wall: list[float]
    """Wall-clock time per solve (s)."""
    cpu: list[float]
    """CPU time of this thread per solve (s): without the time other processes held the
    CPU (on a shared machine they preempt at random; the wall clock counts it)."""
    u0: list[float]
    iters: list[int]
    fails: int


def time_warm(
    model: ControlModel,
    cfg: ControlConfig,
    seq: list[tuple[str, QpInputs]],
    compiled: bool = True,
) -> WarmRun:
    s = MpcSolver(model, cfg, compiled=compiled)
    run = WarmRun([], [], [], [], 0)
    for mode, inp in seq:
        c0 = time.thread_time()
        t0 = time.perf_counter()
        r = s.solve(mode, inp)
        run.wall.append(time.perf_counter() - t0)
        run.cpu.append(time.thread_time() - c0)
        run.u0.append(r.u0 if r.ok else float("nan"))
        run.iters.append(r.iterations)
        run.fails += not r.ok
    return run


def time_cold(
    model: ControlModel, cfg: ControlConfig, seq: list[tuple[str, QpInputs]]
) -> list[float]:
    s = MpcSolver(model, cfg)  # only for P, A and the vectors
    qp = s.qp
    p_triu = {m: sp.triu(qp.P[m], format="csc") for m in qp.P}
    settings = osqp_settings(cfg)  # the controller's, without its time budget
    del settings["time_limit"]
    times = []
    for mode, inp in seq:
        q, lo, hi = qp.vectors(mode, inp)
        t0 = time.perf_counter()
        solver = osqp.OSQP()
        solver.setup(p_triu[mode], q, qp.A, lo, hi, **settings)
        solver.solve(raise_error=False)
        times.append(time.perf_counter() - t0)
    return times


def time_cvxpy(
    model: ControlModel, cfg: ControlConfig, seq: list[tuple[str, QpInputs]]
) -> tuple[list[float], list[float]]:
    import cvxpy as cp  # the bench extra (pip install -e '.[bench]'); --paths needs none

    qp = MpcSolver(model, cfg).qp
    _, lo0, hi0 = qp.vectors(seq[0][0], seq[0][1])
    has_lo, has_hi = lo0 > -1e20, hi0 < 1e20
    a = qp.A.tocsr()
    z = cp.Variable(qp.lay.nz)
    q_par = cp.Parameter(qp.lay.nz)
    lo_par = cp.Parameter(int(has_lo.sum()))
    hi_par = cp.Parameter(int(has_hi.sum()))
    problems = {}
    for mode in qp.P:
        p = cp.psd_wrap(qp.P[mode])
        problems[mode] = cp.Problem(
            cp.Minimize(0.5 * cp.quad_form(z, p) + q_par @ z),
            [a[has_lo] @ z >= lo_par, a[has_hi] @ z <= hi_par],
        )
    times, u0 = [], []
    for mode, inp in seq:
        q, lo, hi = qp.vectors(mode, inp)
        if not (np.array_equal(lo > -1e20, has_lo) and np.array_equal(hi < 1e20, has_hi)):
            raise SystemExit("benchmark sequence changes its constraint pattern")
        t0 = time.perf_counter()
        q_par.value, lo_par.value, hi_par.value = q, lo[has_lo], hi[has_hi]
        problems[mode].solve(solver=cp.CLARABEL)
        times.append(time.perf_counter() - t0)
        u0.append(float(z.value[qp.lay.u0]) if z.value is not None else float("nan"))
    return times, u0


def compare_paths(tc: TruckConfig, cycles: int, repeats: int) -> dict[str, Any]:
    """The compiled and the Python path on the same QPs, replays alternating (``--paths``)."""
    cfg = dataclasses.replace(tc.control, horizon=40)
    seq = record_sim_sequence(tc, cfg, cycles)
    model = ControlModel(tc.vehicle)
    runs: dict[str, list[WarmRun]] = {"compiled": [], "python": []}
    for _ in range(repeats):
        for path in runs:
            runs[path].append(time_warm(model, cfg, seq, compiled=path == "compiled"))
    us = lambda xs, q: float(np.percentile(np.array(xs) * 1e6, q))  # noqa: E731
    out: dict[str, Any] = {"horizon": 40, "move_blocks": cfg.move_blocks, "qps": len(seq)}
    for path, rs in runs.items():
        wall = [x for r in rs for x in r.wall]
        cpu = [x for r in rs for x in r.cpu]
        out[path] = {
            "warm_us_p50": us(wall, 50),
            "warm_us_p99": us(wall, 99),
            "warm_us_p99_best_replay": min(us(r.wall, 99) for r in rs),
            "warm_cpu_us_p50": us(cpu, 50),
            "warm_cpu_us_p99": us(cpu, 99),
            "iters_p50": float(np.median(rs[0].iters)),
            "iters_p99": float(np.percentile(rs[0].iters, 99)),
            "failures": sum(r.fails for r in rs),
        }
    # The first moves compared without the time budget: a solve cut by it on a loaded
    # machine (in one path, not the other) changes the warm start of the next ones.
    free = dataclasses.replace(cfg, time_budget_s=float("inf"))
    u_c = np.array(time_warm(model, free, seq, compiled=True).u0)
    u_p = np.array(time_warm(model, free, seq, compiled=False).u0)
    out["max_abs_diff_u0_compiled_python"] = float(np.max(np.abs(u_c - u_p)))
    out["machine"] = {
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "osqp": osqp.__version__,
        "loadavg_1_5_15": list(os.getloadavg()),
    }
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results as JSON to this file")
    ap.add_argument("--cycles", type=int, default=1200, help="QPs per horizon (12 s at 100 Hz)")
    ap.add_argument("--cvxpy-cycles", type=int, default=150, help="QPs solved by cvxpy")
    ap.add_argument("--repeats", type=int, default=3, help="replays of the warm solver")
    ap.add_argument(
        "--sequence",
        choices=("sim", "ideal"),
        default="sim",
        help="QPs from truckd sim's stop-and-go (estimator, firmware; default) or from a "
        "loop on ideal estimates",
    )
    ap.add_argument("--paths", action="store_true", help="compiled vs Python path only")
    ap.add_argument("--key", metavar="NAME", help="with --paths: the key (what_YYYY-MM-DD)")
    args = ap.parse_args(argv)
    tc = load_config()
    if args.paths:
        r = compare_paths(tc, args.cycles, args.repeats)
        for path in ("compiled", "python"):
            x = r[path]
            print(f"{path:9} warm p50 {x['warm_us_p50']:.0f} us, p99 {x['warm_us_p99']:.0f} us "
                  f"(best replay {x['warm_us_p99_best_replay']:.0f}, CPU p99 "
                  f"{x['warm_cpu_us_p99']:.0f}), iterations {x['iters_p50']:.0f} / "
                  f"{x['iters_p99']:.0f}")  # fmt: skip
        print(f"max |u0 compiled - python| {r['max_abs_diff_u0_compiled_python']:.1e} V, "
              f"load {r['machine']['loadavg_1_5_15'][0]:.2f}")  # fmt: skip
        if args.json:
            write_json(args.json, r, args.key)
        return 0
    model = ControlModel(tc.vehicle)
    rows = []
    for n in (20, 40, 80):
        cfg = dataclasses.replace(tc.control, horizon=n)
        if args.sequence == "sim":
            seq = record_sim_sequence(tc, cfg, args.cycles)
        else:
            seq = record_sequence(model, cfg, args.cycles)
        # Both formulations on the same sequence, replays alternating between them (so
        # both see the same load on a shared machine), with fresh solvers: the pooled
        # percentiles are reported, the best replay's p99 and the CPU-time p99 beside them
        # (other jobs preempt at random, and the wall clock counts it).
        cfgs = {
            "blocked": dataclasses.replace(cfg, move_blocks=cfg.move_blocks or 8),
            "sparse": dataclasses.replace(cfg, move_blocks=0),
            "sparse_1e-5": dataclasses.replace(cfg, move_blocks=0, eps=SPARSE_EPS_UNTIL_2026_11_23),
        }
        runs: dict[str, list[WarmRun]] = {f: [] for f in cfgs}
        for _ in range(args.repeats):
            for form, c in cfgs.items():
                runs[form].append(time_warm(model, c, seq))
        sparse_cfg = cfgs["sparse"]
        cold = time_cold(model, sparse_cfg, seq[: args.cvxpy_cycles * 2])
        # cvxpy on a stride through the sequence (it is slow); compare first moves there.
        stride = max(1, len(seq) // args.cvxpy_cycles)
        idx = list(range(0, len(seq), stride))[: args.cvxpy_cycles]
        cvx, u_cvx = time_cvxpy(model, sparse_cfg, [seq[k] for k in idx])
        us = lambda xs, q: float(np.percentile(np.array(xs) * 1e6, q))  # noqa: E731
        for form, form_runs in runs.items():
            u_warm = form_runs[0].u0
            diffs = [abs(u_warm[k] - u) for k, u in zip(idx, u_cvx, strict=True)]
            diffs = [d for d in diffs if np.isfinite(d)]
            pooled = [x for r in form_runs for x in r.wall]
            pooled_cpu = [x for r in form_runs for x in r.cpu]
            rows.append(
                {
                    "horizon": n,
                    "formulation": form,
                    "move_blocks": cfgs[form].move_blocks,
                    "warm_us_p50": us(pooled, 50),
                    "warm_us_p99": us(pooled, 99),
                    "warm_us_p99_best_replay": min(us(r.wall, 99) for r in form_runs),
                    "warm_cpu_us_p50": us(pooled_cpu, 50),
                    "warm_cpu_us_p99": us(pooled_cpu, 99),
                    "replays": args.repeats,
                    "cold_us_p50": us(cold, 50),
                    "cvxpy_us_p50": us(cvx, 50),
                    "max_abs_diff_u": max(diffs) if diffs else None,
                    "warm_iters_p50": float(np.median(form_runs[0].iters)),
                    "warm_iters_p99": float(np.percentile(form_runs[0].iters, 99)),
                    "warm_failures": sum(r.fails for r in form_runs),
                    "qps": len(seq),
                    "cvxpy_qps": len(idx),
                }
            )
    print(CVXPY_NOTE)
    print(f"QP sequence: {args.sequence} (stop-and-go, {args.cycles} cycles)")
    print(f"load average (1, 5, 15 min): {os.getloadavg()}")
    print(
        f"{'N':>4} {'form':>9} {'warm p50 us':>12} {'warm p99 us':>12} "
        f"{'best p99':>9} {'cpu p99':>8} "
        f"{'cold p50 us':>12} {'cvxpy p50 us':>13} {'speedup':>8} {'max|du0| V':>11} "
        f"{'iters':>6} {'it p99':>6} {'fails':>6}"
    )
    for r in rows:
        print(
            f"{r['horizon']:>4} {r['formulation']:>9} {r['warm_us_p50']:>12.0f} "
            f"{r['warm_us_p99']:>12.0f} "
            f"{r['warm_us_p99_best_replay']:>9.0f} {r['warm_cpu_us_p99']:>8.0f} "
            f"{r['cold_us_p50']:>12.0f} {r['cvxpy_us_p50']:>13.0f} "
            f"{r['cvxpy_us_p50'] / r['warm_us_p50']:>7.0f}x {r['max_abs_diff_u']:>11.2e} "
            f"{r['warm_iters_p50']:>6.0f} {r['warm_iters_p99']:>6.0f} {r['warm_failures']:>6}"
        )
    if args.json:
        doc = {
            "machine": {
                "platform": platform.platform(),
                "python": sys.version.split()[0],
                "cpus": os.cpu_count(),
                "osqp": osqp.__version__,
                "cvxpy": importlib.metadata.version("cvxpy"),
                "loadavg_1_5_15": list(os.getloadavg()),
            },
            "measured": CVXPY_NOTE,
            "sequence": args.sequence,
            "results": rows,
        }
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
