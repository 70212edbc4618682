"""The controller's per-cycle numerics around the MPC in the same compiled call as its solve
(truckd/control/kernel/cycle_numerics.c, in the library :mod:`truckd.control.ccycle` loads).

One ctypes call per cycle computes what :class:`truckd.control.controller.Controller`'s
Python path computes from the estimate to the command: the friction feedforward, the QP's
initial state and inputs and their checks, the MPC cycle (fill, warm start, OSQP's solve,
plan), and from a usable solution the command: breakaway at rest, no reversing from rest,
finite, rate limit, the voltage limit.  The Python path stays the reference and the
fallback (tests/test_cycle_numerics.py: the same commands on the recorded replay).

Every constant comes from the model and the configuration here, at bind time
(:data:`CONSTANTS`): the C file has none of its own.  The compiled numerics serve the
models whose feedforward torque terms are at most aero drag and a constant load (no
terrain, no Stribeck curve), without an input delay and without the driver's maps
(battery sag, dead zone, current limit); for the others :func:`bind` says why not and
the controller runs them in Python (the MPC's solve still compiled).  Loading is
:mod:`truckd.control.ccycle`'s; this module computes nothing itself.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence

import numpy as np

from truckd.control import ccycle
from truckd.control.cestimator import CompiledEstimator
from truckd.control.config import ControlConfig
from truckd.control.effect_use import EFFECT_USES, torque_terms
from truckd.control.estimator import EncoderSample, Estimate, RangeSample
from truckd.control.feedforward import breakaway_feedforward
from truckd.control.mpc import MpcResult, MpcSolver
from truckd.control.qp import INPUT_LIMIT, ControlModel

CONSTANTS = (
    "R_m",
    "K_T",
    "K_coulomb",
    "K_v",
    "ratio",
    "moving_speed",
    "feedforward",
    "breakaway_v",
    "start_voltage",
    "u_max",
    "du",
    "v_max",
    "input_limit",
    "time_budget_s",
    "has_aero_drag",
    "aero_drag",
    "has_load_force",
    "load_force",
    "d_0",
    "time_headway",
    "follow_window",
    "v_set",
    "cruise_on_lead_lost",
    "hold_lead_speed",
    "hold_gap_tol",
    "disturbance_gain",
    "disturbance_max",
    "b_v",
    "saturated_v",
)
"""The constants ``truckd_numerics_bind`` takes, in its order (see :func:`constants`)."""

_DRAG, _LOAD = EFFECT_USES["aero_drag"].torque, EFFECT_USES["load_force"].torque
"""The feedforward torque terms the compiled numerics compute (aero drag, constant load)."""

MODES = ("follow", "cruise", "stop")
"""The controller's modes by ``truckd_cycle_run``'s code."""

N_IN_FIXED = 7
"""Per-cycle inputs before the lead's speeds: v (m/s), gap as the QP sees it (m), the
voltage acting now (V), the disturbance voltage (V), the winding's resistance over R_m,
the highest voltage the driver applies (V), the speed reference (m/s)."""


def constants(
    model: ControlModel,
    cfg: ControlConfig,
    u_max: float,
    du: float,
    time_budget_s: float,
    b_v: float = math.nan,
    saturated_v: float = math.nan,
) -> list[float]:
    """:data:`CONSTANTS`' values from the model and the configuration (``u_max`` V, ``du``
    V per period and the solve's ``time_budget_s`` s as the controller and its MPC have
    them; ``b_v`` its speed per volt over one step, m/s/V, ``saturated_v`` V, as the
    controller's offset-free action has them)."""
    p, eff = model.params, model.effects
    named = {
        "R_m": p.R_m,
        "K_T": p.K_T,
        "K_coulomb": p.K_coulomb,
        "K_v": p.K_v,
        "ratio": p.ratio,
        "moving_speed": cfg.moving_speed,
        "feedforward": 1.0 if cfg.feedforward else 0.0,
        # without the terrain's term the breakaway voltage is the same at every position
        "breakaway_v": breakaway_feedforward(p, eff, cfg.stiction_margin, 0.0),
        "start_voltage": cfg.start_voltage,
        "u_max": u_max,
        "du": du,
        "v_max": cfg.v_max,
        "input_limit": INPUT_LIMIT,
        "time_budget_s": time_budget_s,
        # the feedforward's torque terms the C serves, each on when the model has it
        "has_aero_drag": 1.0 if _DRAG in torque_terms(eff) else 0.0,
        "aero_drag": eff.aero_drag,
        "has_load_force": 1.0 if _LOAD in torque_terms(eff) else 0.0,
        "load_force": eff.load_force,
        # the controller's decisions before the solve (truckd_cycle_run)
        "d_0": cfg.d_0,
        "time_headway": cfg.time_headway,
        "follow_window": cfg.follow_window,
        "v_set": cfg.v_set,
        "cruise_on_lead_lost": 1.0 if cfg.on_lead_lost == "cruise" else 0.0,
        "hold_lead_speed": cfg.hold_lead_speed,
        "hold_gap_tol": cfg.hold_gap_tol,
        "disturbance_gain": cfg.disturbance_gain,
        "disturbance_max": cfg.disturbance_max,
        "b_v": b_v,
        "saturated_v": saturated_v,
    }
    return [float(named[k]) for k in CONSTANTS]


def unsupported(model: ControlModel, delay_steps: int) -> str:
    """Why the compiled numerics cannot compute this model's commands ("" : they can)."""
    eff = model.effects
    if any(t not in (_DRAG, _LOAD) for t in torque_terms(eff)):
        return "the model's feedforward has terrain or Stribeck torque terms"
    if delay_steps > 0:
        return "the model has an input delay"
    for name in ("battery_sag", "dead_zone", "dead_zone_offset", "current_limit"):
        if not getattr(eff, name) <= 0.0:  # as the controller's maps decide (NaN: on)
            return f"the model has the driver map {name}"
    return ""


class CompiledNumerics:
    """The compiled numerics bound to one MPC solver's compiled cycle (see :func:`bind`)."""

    def __init__(self, mpc: MpcSolver, cc: ccycle.CompiledCycle, consts: list[float]) -> None:
        self._mpc = mpc
        self._cc = cc
        n = mpc.horizon
        self.inputs = np.zeros(N_IN_FIXED + n)
        """The cycle's inputs (:data:`N_IN_FIXED`, then the lead's speeds, m/s)."""
        self.out = np.zeros(4)
        """``[command (V), feedforward (V), voltage acting (V), finished (1/0)]``."""
        self._consts = np.array(consts)
        self._pack = struct.Struct(f"={self.inputs.size}d").pack_into
        self._in_mv = self.inputs.data
        lib = cc.lib
        flag = lib.truckd_numerics_bind(
            cc.instance,
            int(self._consts.ctypes.data),
            len(consts),
            int(self.inputs.ctypes.data),
            int(cc.values.ctypes.data),
            int(self.out.ctypes.data),
            int(cc.u.ctypes.data),
            int(cc.info.ctypes.data),
            n,
        )
        if flag != 0:
            raise RuntimeError(f"truckd_numerics_bind refused ({flag})")
        self._run = lib.truckd_numerics_run
        self._instance = cc.instance
        self.decisions_in = np.zeros(8)
        """``truckd_cycle_run``'s decisions' inputs (:meth:`run_cycle`)."""
        self.decisions_out = np.zeros(4)
        """``[mode (MODES), lead (1/0), gap_ref (m), disturbance (V)]`` it decided."""
        self._pack_d = struct.Struct("=8d").pack_into
        self._d_mv = self.decisions_in.data
        flag = lib.truckd_cycle_bind(
            cc.instance, int(self.decisions_in.ctypes.data), int(self.decisions_out.ctypes.data)
        )
        if flag != 0:
            raise RuntimeError(f"truckd_cycle_bind refused ({flag})")
        self._run_cycle = lib.truckd_cycle_run

    def run(
        self, mode: int, lead: bool, state: tuple[float, ...], v_lead: list[float]
    ) -> tuple[MpcResult, list[float]]:
        """One cycle: ``mode`` the QP's (0 follow, 1 cruise), ``state`` the
        :data:`N_IN_FIXED` inputs, ``v_lead`` the lead's speeds over the horizon (m/s,
        Python floats).  Returns the MPC's outcome (as :meth:`MpcSolver.solve`'s) and
        :attr:`out` as Python floats (the command's fields when the outcome is ok; else
        the feedforward, V, for the fallback)."""
        self._pack(self._in_mv, 0, *state, *v_lead)
        how = self._cc.how(mode, lead, self._mpc.has_warm_start)
        res = self._mpc.compiled_outcome(int(self._run(self._instance, how)))
        return res, self.out.tolist()

    def run_cycle(
        self,
        estimator: CompiledEstimator,
        t: float,
        encoders: Sequence[EncoderSample],
        ranges: Sequence[RangeSample],
        decisions: tuple[float, ...],
    ) -> tuple[int, Estimate]:
        """The estimator's update on the cycle's samples (at caller time ``t``, s), the
        controller's decisions and :meth:`run`'s numerics in one call.  ``decisions``:
        the time headway (s), the voltage acting now (V), the speed the last plan
        expected (m/s, NaN: none), whether the last command was current-limited (1/0), the
        voltage it was meant to apply (V), the highest voltage the driver applies (V), the
        disturbance estimate (V), the winding's resistance over R_m.  Returns the call's
        status (:data:`~truckd.control.ccycle.ESTIMATED`: only the estimate, the rest is
        the Python controller's; else :meth:`outcome`'s) and the estimate."""
        estimator.put(t, encoders, ranges)
        self._pack_d(self._d_mv, 0, *decisions)
        how = self._cc.how(0, False, self._mpc.has_warm_start) | 32
        status: int = self._run_cycle(self._instance, how)  # an int (restype c_int64)
        return status, estimator.read()

    def outcome(self, status: int) -> tuple[MpcResult, list[float]]:
        """The MPC's outcome of :meth:`run_cycle`'s solve and :attr:`out` (as :meth:`run`)."""
        return self._mpc.compiled_outcome(status), self.out.tolist()


def bind(
    mpc: MpcSolver, model: ControlModel, cfg: ControlConfig, u_max: float, du: float,
    delay_steps: int, b_v: float = math.nan, saturated_v: float = math.nan,
) -> tuple[CompiledNumerics | None, str]:  # fmt: skip
    """The compiled numerics for a controller's MPC solver, or None and why not (its MPC
    runs the Python path, or the model needs what only the Python path computes)."""
    cc = mpc.compiled_cycle
    if cc is None:
        return None, "the MPC runs its Python path"
    why = unsupported(model, delay_steps)
    if why:
        return None, why
    consts = constants(model, cfg, u_max, du, mpc.cfg.time_budget_s, b_v, saturated_v)
    return CompiledNumerics(mpc, cc, consts), ""
