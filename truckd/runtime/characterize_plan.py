"""``truckd characterize``: the routine's schedule and records: the experiments it plans
(SysId's set, alternately forward and back), what it sees each cycle, the bring-up checks'
outcome, the progress it publishes and the result it ends with.  Data only: the routine
that drives them is :mod:`truckd.runtime.characterize`, the checks
:mod:`truckd.runtime.characterize_checks`."""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

from truckd.config.characterize import CharacterizeConfig
from truckd.control.supervisor import Decision
from truckd.jsonsafe import json_number

EXIT_DONE, EXIT_CHECK, EXIT_STOPPED = 0, 3, 4
"""Exit codes of ``truckd characterize`` (completed, a bring-up check failed, stopped)."""

PAUSE_S = 0.3
"""Rest between experiments (not in the experiment log: each experiment is its own run)."""


@dataclass(frozen=True)
class TruckFacts:
    """What the routine knows of the truck it drives, from the configuration and the DBC."""

    period: float
    """The control period (s)."""
    range_max: float
    """The range sensor's farthest valid reading (m)."""
    encoder_period: float
    """The wheel encoders' message period (s, the DBC's)."""
    ticks_per_rev: int
    """Encoder counts per wheel revolution."""
    r_w: float
    """The configured wheel radius (m)."""


@dataclass(frozen=True)
class Check:
    """One bring-up check: ``detail`` says what was measured, or what to fix."""

    name: str
    ok: bool
    detail: str

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "ok": self.ok, "detail": self.detail}


class CheckFailedError(Exception):
    """A bring-up check failed (the routine stops the truck and ends, exit 3)."""

    def __init__(self, check: Check) -> None:
        super().__init__(check.detail)
        self.check = check


@dataclass
class Experiment:
    """One experiment: its voltage profile and what happened."""

    name: str
    kind: str  # quasistatic | dynamic | validation
    direction: int  # 1 forward, -1 back, 0 both (chirp)
    duration_s: float
    level_v: float = 0.0  # ramp rate (V/s) or step / chirp amplitude (V)
    t_start: float = math.nan
    t_end: float = math.nan
    ended: str = ""  # "" duration reached | "distance budget" | "speed limit" | "stopped"
    skipped: str = ""
    distance_m: float = 0.0

    def voltage(self, tau: float, cfg: CharacterizeConfig) -> float:
        """The voltage at ``tau`` s into the experiment."""
        if self.kind == "quasistatic":  # up, then back down to 0 V at the end
            return self.direction * self.level_v * max(0.0, min(tau, self.duration_s - tau))
        if self.kind == "dynamic":
            return self.direction * self.level_v
        f0, f1, dur = cfg.validation_f0_hz, cfg.validation_f1_hz, self.duration_s
        phase = 2.0 * math.pi * (f0 * tau + 0.5 * (f1 - f0) * tau * tau / dur)
        return self.level_v * math.sin(phase)

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "t_start": json_number(self.t_start),
            "t_end": json_number(self.t_end),
            "ended": self.ended or "done",
            "skipped": self.skipped or None,
            "distance_m": self.distance_m,
        }


def plan_experiments(cfg: CharacterizeConfig) -> list[Experiment]:
    """The experiments in order: alternately forward and back, so the truck stays near
    its start."""
    out = [
        Experiment(f"quasistatic-{name}", "quasistatic", d, cfg.quasistatic_duration_s,
                   cfg.quasistatic_ramp_v_per_s)
        for d, name in ((1, "forward"), (-1, "reverse"))
    ]  # fmt: skip
    for level in cfg.step_voltages:
        for d, name in ((1, "forward"), (-1, "reverse")):
            out.append(
                Experiment(f"dynamic-{name}-{level:g}V", "dynamic", d, cfg.step_duration_s, level)
            )
    out.append(
        Experiment("validation-chirp", "validation", 0, cfg.validation_duration_s, cfg.chirp_v)
    )
    return out


@dataclass
class Obs:
    """What the routine sees in one cycle."""

    t: float
    v: float  # m/s, the estimator's (0 when it has none)
    x: float  # m, encoder distance from the start
    vbat: float
    range_m: float | None  # the last range reading (None: no target in range)
    range_t: float  # the cycle time the last range reading arrived
    encoder_msgs: int  # encoder messages this cycle
    decision: Decision  # the supervisor's, previous cycle


@dataclass
class Progress:
    """What is published on ``truckd/<id>/characterize`` and printed."""

    stage: str = "starting"
    experiment: str = ""
    percent: float = 0.0

    def as_dict(self, t: float) -> dict[str, Any]:
        return {
            "t": t,
            "stage": self.stage,
            "experiment": self.experiment,
            "percent": round(self.percent, 1),
        }


@dataclass
class Result:
    """The routine's outcome."""

    code: int = EXIT_DONE
    checks: list[Check] = field(default_factory=list)
    experiments: list[Experiment] = field(default_factory=list)
    stop_reason: str = ""
    stop_t: float = math.nan
    distance_m: float = 0.0
    duration_s: float = 0.0
    end_speed_m_s: float = math.nan


Script = Generator[float, Obs, None]
"""A stage of the routine: sends the cycle's :class:`Obs`, yields the voltage."""
