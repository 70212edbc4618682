"""Faults the daemon injects into itself for the HIL campaign: a failing solver and an
overrunning loop.  Off unless ``runtime.fault_injection`` is true; switched at run time
by JSON messages on ``truckd/<vehicle_id>/inject``:

``{"fault": "solver", "on": bool}``, ``{"fault": "overrun", "on": bool, "extra_s": S}``,
``{"fault": "clear"}``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from truckd.control.mpc import MpcResult

log = logging.getLogger("truckd.faults")


@dataclass
class RuntimeFaults:
    """Switches read by the loop (plain attributes: set from Zenoh's thread)."""

    solver_fail: bool = False
    overrun_s: float = 0.0  # extra time spent in each cycle, s
    commands: int = 0
    rejected: int = 0

    def apply(self, payload: bytes) -> None:
        """Apply one JSON command; malformed ones are counted and logged."""
        try:
            cmd = json.loads(payload)
            if not isinstance(cmd, dict):
                raise ValueError("expected a JSON object")
            self._apply(cmd)
        except (ValueError, TypeError) as exc:
            self.rejected += 1
            log.warning("fault injection command rejected: %s", exc)
            return
        self.commands += 1
        log.warning("fault injection: %s", cmd)

    def _apply(self, cmd: dict[str, Any]) -> None:
        kind, on = cmd.get("fault"), bool(cmd.get("on", True))
        if kind == "clear":
            self.solver_fail, self.overrun_s = False, 0.0
        elif kind == "solver":
            self.solver_fail = on
        elif kind == "overrun":
            extra = cmd.get("extra_s", 0.03)
            if not isinstance(extra, int | float) or not (math.isfinite(extra) and 0 <= extra <= 1):
                raise ValueError(f"overrun: extra_s must be in [0, 1] s, got {extra!r}")
            self.overrun_s = float(extra) if on else 0.0
        else:
            raise ValueError(f"unknown fault {kind!r}; expected solver, overrun or clear")


def wrap_solver(solve: Callable[..., MpcResult], faults: RuntimeFaults) -> Callable[..., MpcResult]:
    """``solve`` that fails (status ``injected``) while ``faults.solver_fail`` is set."""

    def solve_or_fail(*args: Any, **kwargs: Any) -> MpcResult:
        if faults.solver_fail:
            return MpcResult(False, math.nan, "injected", 0, 0.0)
        return solve(*args, **kwargs)

    return solve_or_fail
