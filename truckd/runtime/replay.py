"""Replay, as openpilot does: a recorded run's inputs fed back through the control cycle.

The daemon records what it did (the CSV log) and, with ``runtime.recorder.messages``,
what it heard (the received-message log, :mod:`truckd.runtime.rxlog`).  :func:`replay`
builds a :class:`~truckd.runtime.cycle.CompanionCycle` from the parameters recorded in
that log and steps it through every recorded cycle; :func:`compare` sets the replayed
commands beside the logged ones.  The solver is judged by what it did (no wall-clock
budget), so a replay reproduces every cycle whose solve met the time budget on the car.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from truckd.control.config import ControlConfig
from truckd.control.qp import ControlModel
from truckd.control.supervisor import SupervisorConfig
from truckd.errors import InputError
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.runtime.cycle import MODE_CODE, CompanionCycle, CycleOutputs
from truckd.runtime.rxlog import read_rx_log
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
    except (KeyError, TypeError) as exc:
        raise InputError(f"{source}: line 1: parameters incomplete: missing {exc}") from None
    return CompanionCycle(model, control, sup, ticks, ramp, time_budget=False, t0=t0)


def replay(path: str | Path) -> list[CycleOutputs]:
    """Every recorded cycle of a received-message log, stepped again."""
    t0, params, cycles = read_rx_log(path)
    cyc = cycle_from_params(params, t0, str(path))
    return [cyc.step(inp) for inp in cycles]


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
    if len(seq) == 0 or seq.max() >= len(outs) or seq.min() < 0:
        raise InputError(f"{log.source}: seq outside the {len(outs)} replayed cycles")
    u = np.array([outs[k].command.voltage for k in seq])
    en = np.array([float(outs[k].command.enable) for k in seq])
    mode = np.array([float(MODE_CODE[outs[k].mode]) for k in seq])
    return Comparison(
        len(seq),
        float(np.max(np.abs(u - log["u"]))),
        int(np.sum(en != log["enable"])),
        int(np.sum(mode != log["mode"])),
    )
