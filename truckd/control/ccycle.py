"""The MPC's compiled cycle (truckd/control/kernel/mpc_cycle.c and OSQP's generated embedded
solver) through ctypes, when built; the controller's numerics around it
(truckd/control/kernel/cycle_numerics.c, in the same library) are bound by
:mod:`truckd.control.cnumerics`.

``make firmware`` builds it (truckd/control/kernel/Makefile: OSQP's code generation for the
shipped QP, then one shared library); without it, or for a QP of another shape or
sparsity pattern, :class:`truckd.control.mpc.MpcSolver` runs its Python path (the
reference: the same commands, checked on a recorded replay by tests/test_mpc_compiled.py).
Why the compiled path is or is not used is one line (:attr:`MpcSolver.backend`), logged
at start-up.  Loading the library is the only thing this module does besides computing.

OSQP's generated workspaces are static: the library has a few instances (4 as generated),
each held by one :class:`CompiledCycle` (:func:`claim`) until its solver is gone; a solver
beyond them in the same process (a fifth truck in one simulation) runs the Python path.
"""

from __future__ import annotations

import ctypes
import gc
import struct
import weakref
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from truckd.control.condensed import N_SCALARS, CondensedQp
from truckd.control.qp import MODES, NX

Vec = NDArray[np.float64]

LIBRARY = Path(__file__).resolve().parent / "kernel" / "build" / "libtruckd_mpc.so"
"""Where ``make firmware`` puts the compiled cycle."""

ABI = 10
"""The interface version this module speaks (``truckd_mpc_abi`` of the library)."""

BAD_INPUT = -100
"""``truckd_numerics_run``'s status for inputs refused before the solve (qp.inputs_ok)."""

ESTIMATED = -101
"""``truckd_cycle_run``'s status when it stopped after the estimator's update (asked to,
or the next decision is the Python controller's)."""

_state: dict[str, object] = {}


def library() -> tuple[ctypes.CDLL | None, str]:
    """The loaded library and "" , or None and why not."""
    if "lib" in _state:
        return _state["lib"], str(_state["why"])  # type: ignore[return-value]
    lib: ctypes.CDLL | None = None
    why = ""
    if not LIBRARY.is_file():
        why = f"{LIBRARY.name} not built (make firmware)"
    else:
        try:
            lib = ctypes.CDLL(str(LIBRARY))
        except OSError as exc:
            why = f"{LIBRARY.name} does not load: {exc}"
    if lib is not None:
        lib.truckd_mpc_abi.restype = ctypes.c_int64
        lib.truckd_mpc_abi.argtypes = []
        if lib.truckd_mpc_abi() != ABI:
            why, lib = f"{LIBRARY.name} speaks another interface (rebuild: make firmware)", None
    if lib is not None:
        try:
            _declare(lib)
        except AttributeError as exc:  # a library of this ABI without every symbol
            why, lib = f"{LIBRARY.name} lacks a symbol ({exc}; rebuild: make firmware)", None
    _state["lib"], _state["why"] = lib, why
    return lib, why


def _declare(lib: ctypes.CDLL) -> None:
    """Every function's argument and result types (AttributeError: a symbol is missing)."""
    i, p, d = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
    lib.truckd_mpc_instances.restype = i
    lib.truckd_mpc_instances.argtypes = []
    lib.truckd_mpc_shape.restype = None
    lib.truckd_mpc_shape.argtypes = [p]
    lib.truckd_mpc_pattern.restype = None
    lib.truckd_mpc_pattern.argtypes = [i, p, p, p, p]
    lib.truckd_mpc_setup.restype = i
    lib.truckd_mpc_setup.argtypes = [i, i, p, p, p, p, p, d, d, i, i, d, d, d, i, d]
    lib.truckd_mpc_set_max_iter.restype = i
    lib.truckd_mpc_set_max_iter.argtypes = [i, i, i]
    lib.truckd_mpc_update_rho.restype = i
    lib.truckd_mpc_update_rho.argtypes = [i, i, d]
    lib.truckd_mpc_bind.restype = i
    lib.truckd_mpc_bind.argtypes = [i, p, p, p, i, i, i, i, p, p, i, i]
    lib.truckd_mpc_bind_io.restype = i
    lib.truckd_mpc_bind_io.argtypes = [i, p, p, p, p, p, p, p, p]
    lib.truckd_mpc_run.restype = i
    lib.truckd_mpc_run.argtypes = [i, i]
    lib.truckd_mpc_bind_plan.restype = i
    lib.truckd_mpc_bind_plan.argtypes = [i, p, d]
    lib.truckd_mpc_plan.restype = i
    lib.truckd_mpc_plan.argtypes = [i]
    lib.truckd_numerics_consts.restype = i
    lib.truckd_numerics_consts.argtypes = []
    lib.truckd_numerics_bind.restype = i
    lib.truckd_numerics_bind.argtypes = [i, p, i, p, p, p, p, p, i]
    lib.truckd_numerics_run.restype = i
    lib.truckd_numerics_run.argtypes = [i, i]
    lib.truckd_estimator_consts.restype = i
    lib.truckd_estimator_consts.argtypes = []
    lib.truckd_estimator_bind.restype = i
    lib.truckd_estimator_bind.argtypes = [i, p, i, p, p, i, i]
    lib.truckd_cycle_bind.restype = i
    lib.truckd_cycle_bind.argtypes = [i, p, p]
    lib.truckd_cycle_run.restype = i
    lib.truckd_cycle_run.argtypes = [i, i]


def _addr(a: NDArray[np.float64] | NDArray[np.int64]) -> int:
    return int(a.ctypes.data)


class CompiledCycle:
    """The compiled cycle bound to one condensed QP (made by :func:`claim`)."""

    def __init__(self, lib: ctypes.CDLL, instance: int, cq: CondensedQp) -> None:
        self._lib = lib
        self.instance = instance
        """Which of the library's instances this is."""
        self.claim_number = 0
        """The claim that holds it (:func:`release`)."""
        self._cq = cq
        nw, m, n = cq.nw, cq.m, cq.qp.lay.N
        keys = [(mode, lead) for mode in MODES for lead in (False, True)]
        # Kept here: the library holds their addresses.
        self._f_span = np.ascontiguousarray(np.stack([cq.span_matrix(k) for k in keys]))
        self._f_const = np.ascontiguousarray(np.stack([cq.const_matrix(k) for k in keys]))
        self._plan_v = np.ascontiguousarray(cq.plan_matrix())
        self._u_block = np.ascontiguousarray(cq.step_blocks(), dtype=np.int64)
        self.values = np.zeros(NX + N_SCALARS + n)
        """The cycle's inputs ``[x0; scalars; v_lead]`` (written by :meth:`put_values`)."""
        self._pack = struct.Struct(f"={self.values.size}d").pack_into
        self._values_mv = self.values.data
        span = cq.span
        lib.truckd_mpc_bind(
            instance,
            _addr(self._f_span),
            _addr(self._f_const),
            _addr(cq.buffer),
            span.start,
            span.stop - span.start,
            self.values.size,
            NX + N_SCALARS + 1,
            _addr(self._plan_v),
            _addr(self._u_block),
            n,
            NX,
        )
        # Two pairs of solution arrays: the solve writes one while the other may hold the
        # warm start; the caller swaps them when it keeps the new solution.
        self._xy = [(np.zeros(nw), np.zeros(m)), (np.zeros(nw), np.zeros(m))]
        self.u = np.zeros(n)
        self.v = np.zeros(n + 1)
        self.info = np.zeros(4)
        """``[status value, iterations, run time (s), all finite (1/0)]`` of the last cycle."""
        (x0, y0), (x1, y1) = self._xy
        arrays = (self.values, x0, y0, x1, y1, self.u, self.v, self.info)
        lib.truckd_mpc_bind_io(instance, *(_addr(a) for a in arrays))
        self.plan = np.zeros(2 * (n + 1))
        """The plan of the last cycle's speeds :attr:`v`: clipped at 0, then their
        accelerations over the period (m/s, m/s^2; as
        :func:`~truckd.control.platoon.plan_of_array` makes them, in the same call)."""
        self.plan_bound = (
            lib.truckd_mpc_bind_plan(instance, _addr(self.plan), cq.qp.cfg.period) == 0
        )
        """Whether the library writes :attr:`plan` (else the plan is made in Python)."""
        self._run = lib.truckd_mpc_run
        self._cur = 0

    @property
    def lib(self) -> ctypes.CDLL:
        """The loaded library."""
        return self._lib

    def how(self, mode: int, lead: bool, warm: bool) -> int:
        """:meth:`cycle`'s arguments as the one integer ``truckd_mpc_run`` and
        ``truckd_numerics_run`` take (one lead speed left for the latter to find)."""
        return mode | lead << 1 | warm << 3 | self._cur << 4

    def setup(
        self,
        mode: int,
        p_x: Vec,
        a_x: Vec,
        eps: float,
        max_iter: int,
        check: int,
        time_limit: float,
        rho: float,
        alpha: float,
        rho_interval: int,
        rho_tolerance: float,
    ) -> int:
        """This truck's matrix values, the vectors :meth:`CondensedQp.fill` left in its
        buffer (the solver's set-up inputs: OSQP scales the cost by them) and the settings
        (``time_limit`` s; the relaxation ``alpha`` and the rho adaptation's interval and
        tolerance replace the generated solver's own) into one mode's solver (0: done)."""
        px = np.ascontiguousarray(p_x, dtype=np.float64)
        ax = np.ascontiguousarray(a_x, dtype=np.float64)
        cq = self._cq
        q, lo, hi = (_addr(a) for a in (cq.q_view, cq.lo_view, cq.hi_view))
        fn = self._lib.truckd_mpc_setup
        args = (eps, eps, max_iter, check, time_limit, rho, alpha, rho_interval, rho_tolerance)
        return int(fn(self.instance, mode, _addr(px), _addr(ax), q, lo, hi, *args))

    def set_max_iter(self, mode: int, max_iter: int) -> None:
        """OSQP's iteration limit of one mode's solver."""
        self._lib.truckd_mpc_set_max_iter(self.instance, mode, max_iter)

    def update_rho(self, mode: int, rho: float) -> None:
        """OSQP's step size back to ``rho`` (refactors the KKT matrix)."""
        self._lib.truckd_mpc_update_rho(self.instance, mode, rho)

    def put_values(self, values: list[float]) -> None:
        """The cycle's inputs (Python floats, as many as :attr:`values` holds) into
        :attr:`values` (one ``struct`` call: the same doubles as a numpy assignment)."""
        self._pack(self._values_mv, 0, *values)

    def cycle(self, mode: int, lead: bool, one_speed: bool, warm: bool) -> int:
        """One cycle on :attr:`values`; warm: from the kept solution (:meth:`keep`).
        Returns OSQP's status value (negative: the call itself failed).  The arguments
        go over as one integer (``truckd_mpc_run``: ctypes converts two, not twelve)."""
        how = mode | lead << 1 | one_speed << 2 | warm << 3 | self._cur << 4
        return int(self._run(self.instance, how))

    def plan_of_v(self) -> None:
        """:attr:`plan` again from :attr:`v` as it is now (each cycle does it itself)."""
        self._lib.truckd_mpc_plan(self.instance)

    def solution(self) -> tuple[Vec, Vec]:
        """The last cycle's ``(x, y)`` (arrays the next cycle but one overwrites)."""
        return self._xy[1 - self._cur]

    def keep(self) -> None:
        """The last cycle's solution becomes the warm start of the next."""
        self._cur = 1 - self._cur


def shape(lib: ctypes.CDLL) -> tuple[int, ...]:
    """``(n, m, nnz P follow, nnz A follow, nnz P cruise, nnz A cruise)`` as generated."""
    out = np.zeros(6, dtype=np.int64)
    lib.truckd_mpc_shape(_addr(out))
    return tuple(int(v) for v in out)


def pattern_matches(lib: ctypes.CDLL, mode: int, p_triu: object, a: object) -> bool:
    """Whether a mode's P (upper triangle, CSC) and A (CSC) have the generated pattern."""
    sh = shape(lib)
    n, nnz_p, nnz_a = sh[0], sh[2 + 2 * mode], sh[3 + 2 * mode]
    pp, pi = np.zeros(n + 1, dtype=np.int64), np.zeros(nnz_p, dtype=np.int64)
    ap, ai = np.zeros(n + 1, dtype=np.int64), np.zeros(nnz_a, dtype=np.int64)
    lib.truckd_mpc_pattern(mode, _addr(pp), _addr(pi), _addr(ap), _addr(ai))
    return all(
        np.array_equal(mine, getattr(mat, field))
        for mat, fields in ((p_triu, (pp, pi)), (a, (ap, ai)))
        for mine, field in zip(fields, ("indptr", "indices"), strict=True)
    )


STATUS_TEXT = (
    "",
    "solved",
    "solved inaccurate",
    "primal infeasible",
    "primal infeasible inaccurate",
    "dual infeasible",
    "dual infeasible inaccurate",
    "maximum iterations reached",
    "run time limit reached",
    "problem non convex",
    "interrupted",
    "unsolved",
)
"""OSQP's status texts by status value (its ``OSQP_STATUS_MESSAGE``, as the Python binding
reports them)."""


def status_text(status_val: int) -> str:
    """OSQP's text of a status value."""
    return STATUS_TEXT[status_val] if 0 < status_val < len(STATUS_TEXT) else f"status {status_val}"


_held: dict[int, int] = {}
"""The instances held by a live solver, each with the number of its claim."""

_claims = [0]


def release(instance: int, claim_number: int) -> None:
    """Give an instance back (the solver of that claim is gone or does not use it); a
    later claim of the instance is left alone."""
    if _held.get(instance) == claim_number:
        del _held[instance]


def claim(owner: object, cq: CondensedQp) -> tuple[CompiledCycle | None, str]:
    """A compiled cycle for ``owner`` (an :class:`~truckd.control.mpc.MpcSolver`, which
    holds it until it is garbage) and its condensed QP, or None and why not (not built,
    another shape or pattern, or every instance held by another live solver)."""
    lib, why = library()
    if lib is None:
        return None, why
    sh = shape(lib)
    if (sh[0], sh[1]) != (cq.nw, cq.m):
        return None, (
            f"generated for a QP of {sh[0]} variables and {sh[1]} rows, this one has "
            f"{cq.nw} and {cq.m} (horizon or move blocks changed)"
        )
    for k, mode in enumerate(MODES):
        if not pattern_matches(lib, k, cq.p_triu(mode), cq.A):
            return None, f"this truck's {mode} QP has another sparsity pattern than the generated"
    count = int(lib.truckd_mpc_instances())
    free = [k for k in range(count) if k not in _held]
    if not free:  # solvers that are garbage in a reference cycle give theirs back
        gc.collect()
        free = [k for k in range(count) if k not in _held]
    if not free:
        return None, f"all {count} compiled instances held by other MPC solvers of this process"
    _claims[0] += 1
    _held[free[0]] = _claims[0]
    weakref.finalize(owner, release, free[0], _claims[0])
    cc = CompiledCycle(lib, free[0], cq)
    cc.claim_number = _claims[0]
    return cc, ""
