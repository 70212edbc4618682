"""Generate OSQP's embedded C solver for the shipped move-blocked QP (run by
truckd/control/kernel/Makefile, which ``make firmware`` runs).

One workspace per cost mode and instance (``follow0_solver``, ``cruise0_solver``, ..; see
:data:`INSTANCES`) in OSQP's embedded mode 2 (vectors and matrix values updatable), for
the shipped configuration's QP: the sparsity pattern and the sizes are fixed by the
horizon and the move blocks; the matrix values of the truck actually driven are written
into it at start-up (:mod:`truckd.control.ccycle`), so one build serves every truck with
the shipped horizon and blocks.  Another shape, or a pattern that differs, runs the Python
path (reported).

    .venv/bin/python tools/generate_mpc_solver.py OUTDIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import osqp

from truckd.config.truck import load_config
from truckd.control.mpc import MpcSolver, codegen_settings
from truckd.control.qp import MODES, ControlModel

INSTANCES = 4
"""Solvers one process can run compiled at once (each its own static workspaces): a test
or a simulation with more trucks runs the others on the Python path."""


FIRST_INFO = "if(can_check_termination || can_print || can_adapt_rho || iter == 1) {"
"""OSQP's solve loop computes its residuals, objective and duality gap (``update_info``)
at the first iteration whatever the settings; nothing reads them before the next
computation overwrites them (the termination check, the rho adaptation and the end of
the solve each compute their own), so the iterates, the solution, the status and the
iteration count are the same without it.  A fifth of ``update_info``'s work in a solve
of 20 iterations checked every 5."""


def _skip_first_info(path: Path) -> None:
    """Leave out the first iteration's residuals (:data:`FIRST_INFO`) from the generated
    solve; another OSQP whose code differs is left as generated (noted on stderr)."""
    text = path.read_text()
    if text.count(FIRST_INFO) != 1:
        print(f"generate_mpc_solver.py: {path.name}: solve loop not as expected, left as is",
              file=sys.stderr)  # fmt: skip
        return
    path.write_text(text.replace(FIRST_INFO, FIRST_INFO.replace(" || iter == 1", "")))


GAP_CALLS = {
    "src/auxil.c": (
        "  compute_obj_val_dual_gap(solver, x, y, prim_obj_val, dual_obj_val, dual_gap);\n",
        "  if (solver->settings->check_dualgap)\n"
        "    compute_obj_val_dual_gap(solver, x, y, prim_obj_val, dual_obj_val, dual_gap);\n"
        "  else\n"
        "    *dual_gap = 0.0;\n",
    ),
    "src/osqp_api.c": (
        "  if (has_solution(solver->info)){\n    compute_obj_val_dual_gap(",
        "  if (has_solution(solver->info) && solver->settings->check_dualgap){\n"
        "    compute_obj_val_dual_gap(",
    ),
}
"""With the duality-gap test off (``check_dualgap`` 0, the move-blocked QP's setting), the
objective and duality gap OSQP computes at every check and after the solve are read by
nothing the cycle uses (OSQP's ``obj_val`` and ``duality_gap`` info, its KKT-error rho
adaptation, which the controller does not use): left out, the iterates, status and
iteration count unchanged.  A third of a termination check's work."""

DENSE_HOOKS = {
    "void OSQPMatrix_Axpy(const OSQPMatrix*  A,\n"
    "                     const OSQPVectorf* x,\n"
    "                           OSQPVectorf* y,\n"
    "                           OSQPFloat    alpha,\n"
    "                           OSQPFloat    beta) {\n": "truckd_dense_Axpy",
    "void OSQPMatrix_Atxpy(const OSQPMatrix*  A,\n"
    "                      const OSQPVectorf* x,\n"
    "                            OSQPVectorf* y,\n"
    "                            OSQPFloat    alpha,\n"
    "                            OSQPFloat    beta) {\n": "truckd_dense_Atxpy",
}
"""OSQP's products with A (``y = A x``, ``y = A' x``: the residuals of every termination
check) first offered to the compiled cycle's dense copy of A (``mpc_cycle.c``), which
computes them over the rows or columns in the order OSQP's sparse loops add them (the same
numbers, vectorised); any other product, or before the dense copy exists, OSQP's own."""


def _dense_products(path: Path) -> None:
    """Hook :data:`DENSE_HOOKS` into the generated matrix products; another OSQP whose code
    differs is left as generated (noted on stderr)."""
    text = path.read_text()
    if any(text.count(head) != 1 for head in DENSE_HOOKS):
        print(f"generate_mpc_solver.py: {path.name}: products not as expected, left as is",
              file=sys.stderr)  # fmt: skip
        return
    for head, hook in DENSE_HOOKS.items():
        decl = (
            f"OSQPInt {hook}(const OSQPMatrix *A, const OSQPFloat *x, OSQPFloat *y, "
            "OSQPFloat alpha, OSQPFloat beta);\n"
        )
        call = f"  if ({hook}(A, x->values, y->values, alpha, beta)) return;\n"
        text = text.replace(head, decl + head + call)
    path.write_text(text)


def _gap_only_when_checked(out: Path) -> None:
    """:data:`GAP_CALLS` into the generated solver; another OSQP whose code differs is left
    as generated (noted on stderr)."""
    for name, (old, new) in GAP_CALLS.items():
        path = out / name
        text = path.read_text()
        if text.count(old) != 1:
            print(f"generate_mpc_solver.py: {name}: gap call not as expected, left as is",
                  file=sys.stderr)  # fmt: skip
            continue
        path.write_text(text.replace(old, new))


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: generate_mpc_solver.py OUTDIR", file=sys.stderr)
        return 2
    out = Path(argv[0]).resolve()
    tc = load_config()
    s = MpcSolver(ControlModel(tc.vehicle), tc.control, compiled=False)
    cq = s.condensed
    if cq is None:
        print("generate_mpc_solver.py: the shipped QP has no move blocks", file=sys.stderr)
        return 2
    table = []
    for k in range(INSTANCES):
        names = []
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
                prefix=f"{mode}{k}_",
                force_rewrite=True,
                profiling_enable=True,  # the run time and the time limit (timing.c)
            )
            names.append(f"{mode}{k}_solver")
        table.append("{" + ", ".join(f"&{n}" for n in names) + "}")
    (out / "emosqp.c").unlink(missing_ok=True)  # OSQP's sample program: not part of the library
    _skip_first_info(out / "src" / "osqp_api.c")
    _dense_products(out / "src" / "matrix.c")
    _gap_only_when_checked(out)
    includes = [f'#include "{mode}{k}_workspace.h"' for k in range(INSTANCES) for mode in MODES]
    (out / "instances.h").write_text(
        "/* Generated by tools/generate_mpc_solver.py: the solver workspaces, by instance and\n"
        f" * mode ({', '.join(MODES)}), for a QP of {cq.nw} variables and {cq.m} rows. */\n"
        + "\n".join(includes)
        + f"\n#define TRUCKD_MPC_INSTANCES {INSTANCES}\n"
        + f"#define TRUCKD_MPC_MODES {len(MODES)}\n"
        + f"#define TRUCKD_MPC_N {cq.nw}\n#define TRUCKD_MPC_M {cq.m}\n"
        + f"#define TRUCKD_MPC_SOLVERS {{{', '.join(table)}}}\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
