"""Replay, as openpilot does: a recorded run's inputs fed back through the control cycle.

The daemon records what it did (the CSV log) and, by default (``runtime.recorder.messages``),
what it heard (the received-message log, :mod:`truckd.runtime.rxlog`, one beside each
rotated CSV file).  :func:`replay` builds a :class:`~truckd.runtime.cycle.CompanionCycle`
from the parameters recorded in that log and steps it through every recorded cycle;
:func:`compare` sets the replayed commands beside the logged ones, matched by cycle number.

The solver is judged by what it did (no wall-clock budget).  A solve that failed on the car
(over its time budget on a loaded core, which no replay can time again) is recorded with the
cycle; the replay solves it and then fails it the same way, so the fallback, the supervisor
and the commands follow the car's.  What cannot be replayed exactly: the warm start such a
solve left behind (the car's unfinished iterate, the replay's converged one), so the next
solves agree within the solver's tolerance (``control.eps``), not to the last digit.

Several files of one run (the recorder rotates them) replay in order as one run.  A file
replayed on its own that is not the run's first (``seq0`` > 0) starts from a fresh state:
its first cycles differ until the estimator and the supervisor have settled.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from truckd.control.config import ControlConfig
from truckd.control.mpc import MpcResult
from truckd.control.qp import ControlModel
from truckd.control.supervisor import SupervisorConfig
from truckd.errors import InputError
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.runtime.cycle import MODE_CODE, CompanionCycle, CycleOutputs
from truckd.runtime.rxlog import Failure, read_rx_recording
from truckd.schema import load_dataclass


def cycle_from_params(params: dict[str, Any], t0: float, source: str) -> CompanionCycle:
    """The companion cycle a recorded run used (its ``params`` header)."""
    try:
        model = ControlModel(
            load_dataclass(VehicleParams, params["model"]["vehicle"], source),
            load_dataclass(Effects, params["model"]["effects"], source),
        )
        # A log recorded before `control.move_blocks` existed ran the sparse QP.
        control_params = {"move_blocks": 0, **params["control"]}
        control = load_dataclass(ControlConfig, control_params, source)
        sup = load_dataclass(SupervisorConfig, params["runtime"]["supervisor"], source)
        ramp = float(params["runtime"]["stop_ramp_v_per_s"])
        ticks = int(params["ticks_per_rev"])
        # A run recorded before `runtime.stall_limit_s` existed detected no stalls.
        stall = float(params["runtime"].get("stall_limit_s", math.inf))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{source}: line 1: parameters incomplete: missing {exc}") from None
    return CompanionCycle(
        model, control, sup, ticks, ramp, time_budget=False, t0=t0, stall_limit_s=stall
    )


class _CarFailures:
    """Wraps the cycle's MPC solve: on a cycle whose solve failed on the car, the solve runs
    and then reports the car's failure (status and iterations)."""

    def __init__(self, cyc: CompanionCycle) -> None:
        self.due: Failure | None = None
        mpc = cyc.controller.mpc
        self._solve = mpc.solve
        mpc.solve = self  # type: ignore[method-assign]

    def __call__(self, *args: Any, **kwargs: Any) -> MpcResult:
        res = self._solve(*args, **kwargs)
        due, self.due = self.due, None
        if due is None or not res.ok:
            return res
        return MpcResult(False, math.nan, due[0], due[1], res.run_time_s)


def replay(paths: str | Path | Sequence[str | Path]) -> list[CycleOutputs]:
    """Every recorded cycle of a received-message log (or of several files of one run,
    in order), stepped again; each output's ``seq`` is the recorded cycle's."""
    files = [paths] if isinstance(paths, str | Path) else list(paths)
    if not files:
        raise InputError("replay: no received-message log given")
    recs = [read_rx_recording(p) for p in files]
    first = recs[0]
    cyc = cycle_from_params(first.params, first.t0, str(first.path))
    cyc.seq = first.seq0
    failures = _CarFailures(cyc)
    outs: list[CycleOutputs] = []
    for rec in recs:
        if rec.seq0 != cyc.seq:
            raise InputError(
                f"{rec.path}: line 1: starts at cycle {rec.seq0}, expected {cyc.seq} (the "
                "files of one run, in order)"
            )
        for inp, failure in rec.records:
            failures.due = failure
            outs.append(cyc.step(inp))
    return outs


@dataclass(frozen=True)
class Comparison:
    """Replayed against logged: cycles compared, the largest voltage difference (V), and
    the cycles whose enable or supervisor mode differ."""

    cycles: int
    max_abs_du: float
    enable_mismatches: int
    mode_mismatches: int


def compare(log: Log, outs: list[CycleOutputs]) -> Comparison:
    """Match the log's rows to the replayed cycles by ``seq`` (InputError when the log
    has cycles the replay has not)."""
    seq = log["seq"].astype(int)
    by_seq = {o.seq: o for o in outs}
    missing = [int(k) for k in seq if int(k) not in by_seq]
    if len(seq) == 0 or missing:
        first = f" (cycle {missing[0]})" if missing else ""
        raise InputError(f"{log.source}: seq outside the {len(outs)} replayed cycles{first}")
    rows = [by_seq[int(k)] for k in seq]
    u = np.array([o.command.voltage for o in rows])
    en = np.array([float(o.command.enable) for o in rows])
    mode = np.array([float(MODE_CODE[o.mode]) for o in rows])
    return Comparison(
        len(seq),
        float(np.max(np.abs(u - log["u"]))),
        int(np.sum(en != log["enable"])),
        int(np.sum(mode != log["mode"])),
    )
