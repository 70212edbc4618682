"""What a diagnosis returns: the JSON of reference section 4 plus report material."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from truckd.model.effects import Effects
from truckd.model.params import VehicleParams

Array = NDArray[np.float64]


@dataclass(frozen=True)
class ModelSummary:
    """Fit of one model on the report data (validation log when given)."""

    fit_percent: float
    rmse: float
    params: dict[str, float]
    force_relerr_percent: float | None = None
    feedforward: dict[str, float] | None = None
    """The model in WPILib SysId's form: kS (V), kV (V s/m), kA (V s^2/m)."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "fit_percent": _num(self.fit_percent),
            "rmse": _num(self.rmse),
            "params": {k: _num(v) for k, v in self.params.items()},
        }
        if self.feedforward is not None:
            out["feedforward"] = {k: _num(v) for k, v in self.feedforward.items()}
        if self.force_relerr_percent is not None:
            out["force_relerr_percent"] = _num(self.force_relerr_percent)
        return out


@dataclass(frozen=True)
class Finding:
    """An accepted effect: its parameters, the fit with it, and the fit it adds."""

    name: str
    params: dict[str, float]
    fit_percent: float
    fit_gain_percent: float
    profile: dict[str, float | str] | None = None
    """Where a position-dependent load acts (``profile``: "hill", ``x_start_m``,
    ``x_end_m``, ``value`` N); None for an effect that does not depend on position."""

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "params": {k: _num(v) for k, v in self.params.items()},
            "fit_percent": _num(self.fit_percent),
            "fit_gain_percent": _num(self.fit_gain_percent),
        }
        if self.profile is not None:
            out.update({k: v if isinstance(v, str) else _num(v) for k, v in self.profile.items()})
        return out


@dataclass(frozen=True)
class CandidateRow:
    """One candidate as tried alone on top of the seed (for the report's table)."""

    name: str
    params: dict[str, float]
    fit_percent: float
    """Validation fit of seed + this candidate (%)."""
    gain_percent: float
    """Its validation fit minus the seed's (percentage points)."""
    cost_ratio: float
    """Validation weighted SSE relative to the seed's (< 1 is better)."""
    delta_bic: float
    """Change of the Bayesian information criterion on the fit data (< 0 is better)."""
    accepted: bool
    note: str = ""


@dataclass(frozen=True)
class Rejected:
    """A best fit outside what is physically possible, with the reason."""

    name: str
    params: dict[str, float]
    reason: str

    def to_json(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "params": {k: _num(v) for k, v in self.params.items()},
            "reason": self.reason,
        }


@dataclass
class Traces:
    """Signals of the report data for the plots (SI)."""

    t: Array
    inp: Array
    y: Array
    y_base: Array
    y_ext: Array
    i: Array | None = None
    x: Array | None = None
    input_name: str = "u"


@dataclass
class Diagnosis:
    """Everything ``diagnose`` found (see :meth:`to_json` for the contract's subset)."""

    input: str
    samples: int
    baseline: ModelSummary
    effects: list[Finding]
    extended: ModelSummary
    unexplained: bool
    ambiguous: list[tuple[str, str]]
    candidates: list[CandidateRow] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    traces: Traces | None = None
    vehicle: VehicleParams | None = None
    """The extended model (voltage-input logs), for MODEL.yaml."""
    model_effects: Effects | None = None
    residual_stats: dict[str, float] = field(default_factory=dict)
    rejected: list[Rejected] = field(default_factory=list)
    """Best fits that are physically impossible: reported, never accepted."""
    linear: dict[str, float] | None = None
    """The linear equation-error estimate (SysId's OLS) the fit started from."""
    least_squares: dict[str, float | None] | None = None
    """The data's own least-squares model (SysId's): kS, kV, kA, their standard errors
    ``*_se`` (None: not determined) and its ``fit_percent`` on the report data."""
    alerts: list[str] = field(default_factory=list)
    """The notes a user must see (a limit that binds, a machine unlike the configured
    one, a fallback to least squares); also in ``notes``."""
    runs: int = 1
    explains: bool = False
    """The extended model's residual is white at the noise level on the report data."""
    fit_ceiling: float | None = None
    """The ``fit_percent`` a model leaving only the measurement noise would reach on the
    report data (:func:`truckd.ident.data.fit_ceiling_percent`); None: the speed is flat."""
    chatter: list[dict[str, float | int | str]] = field(default_factory=list)
    """The stretches of chatter left out (:func:`truckd.ident.chatter.spans_json`)."""
    fit_with_chatter: float | None = None
    """The extended model's ``fit_percent`` on the report data with the chatter left in
    (None: there was none)."""
    position_unit: str = "m"
    """The logs' unit of position: ``m``, or ``rad`` for a rotational SysId log (its
    speed then rad/s, kV in V s/rad, kA in V s^2/rad)."""

    def units(self) -> tuple[str, str, str, str]:
        """The units of speed, kS, kV and kA as printed (``m/s``, ``V``, ``V s/m``,
        ``V s^2/m``; a force-input log's kS, kV, kA are ``N``, ``N s/m``, ``kg``)."""
        if self.input == "force":
            return "m/s", "N", "N s/m", "kg"
        pu = self.position_unit
        return f"{pu}/s", "V", f"V s/{pu}", f"V s^2/{pu}"

    def to_json(self) -> dict[str, Any]:
        """The reference section 4 object (plus ``notes`` and ``residual``)."""
        return {
            "input": self.input,
            "samples": int(self.samples),
            "baseline": self.baseline.to_json(),
            "effects": [f.to_json() for f in self.effects],
            "extended": self.extended.to_json(),
            "unexplained": bool(self.unexplained),
            "ambiguous": [[a, b] for a, b in self.ambiguous],
            "notes": list(self.notes),
            "residual": {k: _num(v) for k, v in self.residual_stats.items()},
            "rejected": [r.to_json() for r in self.rejected],
            "runs": int(self.runs),
            "explains_data": bool(self.explains),
            "fit_ceiling_percent": _opt(self.fit_ceiling),
            "position_unit": self.position_unit,
            "chatter": [dict(c) for c in self.chatter],
            "fit_percent_with_chatter": _opt(self.fit_with_chatter),
            # always present (reference section 4); null when the data cannot give them
            "linear_estimate": self.linear,
            "least_squares": (
                None
                if self.least_squares is None
                else {k: _opt(v) for k, v in self.least_squares.items()}
            ),
        }


def _opt(x: float | None) -> float | None:
    """:func:`_num` that passes None through."""
    return None if x is None else _num(x)


def _num(x: float) -> float | None:
    """A JSON-safe float (None for non-finite)."""
    return float(x) if np.isfinite(x) else None
