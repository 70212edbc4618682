"""Generate OSQP's embedded C solver for the shipped move-blocked QP (run by the Makefile
here, which ``make firmware`` runs).

One workspace per cost mode (``follow_solver``, ``cruise_solver``) in OSQP's embedded mode
2 (vectors and matrix values updatable), for the shipped configuration's QP: the sparsity
pattern and the sizes are fixed by the horizon and the move blocks; the matrix values of
the truck actually driven are written into it at start-up
(:mod:`truckd.control.ccycle`), so one build serves every truck with the shipped horizon
and blocks.  Another shape, or a pattern that differs, runs the Python path (reported).

    .venv/bin/python tools/generate_mpc_solver.py OUTDIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import osqp

from truckd.config.truck import load_config
from truckd.control.mpc import MpcSolver, codegen_settings
from truckd.control.qp import MODES, ControlModel


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: generate_mpc_solver.py OUTDIR", file=sys.stderr)
        return 2
    out = Path(argv[0]).resolve()
    tc = load_config()
    s = MpcSolver(ControlModel(tc.vehicle), tc.control, compiled=False)
    cq = s.condensed
    if cq is None:
        print("generate_mpc_solver.py: the shipped configuration has no move blocks", file=sys.stderr)
        return 2
    for mode in MODES:
        solver = osqp.OSQP()
        cq.fill(mode, s.zero_inputs)
        solver.setup(
            cq.p_triu(mode),
            cq.q_view.copy(),
            cq.A,
            cq.lo_view.copy(),
            cq.hi_view.copy(),
            **codegen_settings(tc.control),
        )
        solver.codegen(
            str(out),
            parameters="matrices",
            extension_name=None,
            prefix=f"{mode}_",
            force_rewrite=True,
        )
    (out / "shape.txt").write_text(f"{cq.nw} {cq.m} {tc.control.horizon} {cq.blocks}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
