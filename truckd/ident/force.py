"""Diagnosis of a force-input log (a current-controlled drive or a test rig, e.g. EMPS).

The seed's structure at the load: ``F = M a + F_c sign(v)`` (inertia + Coulomb).
Candidates add regressors to this inverse dynamic model (IDM):

* ``viscous_friction``: ``F_v v``;
* ``load_force``: a constant ``offset`` (gravity, a spring preload, a force sensor
  offset);
* ``aero_drag``: ``c v |v|``.

Fitted by linear least squares on filtered, differentiated and decimated signals
(the IDIM-LS recipe of the EMPS benchmark: 4th-order Butterworth with zero phase,
central differences, decimation).  The other contract effects concern a voltage drive
and are not candidates here.  Selection mirrors the voltage case: information
criterion on the fit data and the force error on validation data.  Pure numerics.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from truckd.ident.data import Series, fit_ceiling_percent, initial_speed, noise_std, split
from truckd.ident.forcerun import ForceModel, simulate_force
from truckd.ident.linear import ols_covariance
from truckd.ident.residuals import whiteness
from truckd.ident.result import CandidateRow, Diagnosis, Finding, ModelSummary, Traces
from truckd.ident.selection import close, delta_bic, passes, structured
from truckd.ident.voltage import fit_percent, rmse
from truckd.model.effects import EFFECT_NAMES

Array = NDArray[np.float64]


FORCE_CANDIDATES: dict[str, str] = {
    "viscous_friction": "F_v",
    "load_force": "offset",
    "aero_drag": "c_drag",
}
"""Candidate effect -> the IDM parameter it adds (N s/m, N, N/(m/s)^2)."""

NOT_APPLICABLE = tuple(n for n in EFFECT_NAMES if n not in FORCE_CANDIDATES)
"""The effects that concern a voltage drive: not candidates for a force input."""


@dataclass(frozen=True)
class Idm:
    """Regressor columns and force, filtered and decimated in parallel (SI).

    ``cols`` holds ``a`` (acceleration), ``sign`` (sign of speed), ``v`` (speed),
    ``one`` and ``v2`` (``v |v|``), each computed at the full rate and then decimated,
    as the EMPS reference (IDIM-LS with a parallel decimation filter) does.
    """

    F: Array
    cols: dict[str, Array]

    @property
    def v(self) -> Array:
        return self.cols["v"]

    def regressors(self, names: Sequence[str]) -> Array:
        keys = ["a", "sign"]
        for n in names:
            keys.append({"viscous_friction": "v", "load_force": "one", "aero_drag": "v2"}[n])
        return np.column_stack([self.cols[k] for k in keys])


def idm_signals(s: Series) -> Idm:
    """IDIM-LS preprocessing: zero-phase low-pass, central differences, decimation."""
    from scipy.signal import butter, decimate, filtfilt

    h = float(np.median(np.diff(s.t)))
    fs = 1.0 / h
    cutoff = min(100.0, 0.1 * fs)  # Hz; 100 Hz at the EMPS' 1 kHz
    b, a = butter(4, cutoff / (0.5 * fs))
    if s.x is not None:
        xf = filtfilt(b, a, s.x)
        v = np.gradient(xf, h)
    else:
        v = filtfilt(b, a, s.v)
    acc = np.gradient(v, h)
    q = max(1, round(fs / cutoff))  # 10 at the EMPS: the published decimation
    edge = min(49, len(s.t) // 10)
    full = {
        "a": acc,
        "sign": np.sign(v),
        "v": v,
        "one": np.ones_like(v),
        "v2": v * np.abs(v),
    }

    def dec(x: Array) -> Array:
        x = np.asarray(x[edge:], float)
        return np.asarray(decimate(x, q), float) if q > 1 else x

    return Idm(F=dec(s.inp), cols={k: dec(c) for k, c in full.items()})


@dataclass(frozen=True)
class IdmFit:
    names: tuple[str, ...]
    theta: Array
    sse: float
    n: int
    cond: float

    def params(self) -> dict[str, float]:
        out = {"M": float(self.theta[0]), "F_c": float(self.theta[1])}
        for k, n in enumerate(self.names):
            out[FORCE_CANDIDATES[n]] = float(self.theta[2 + k])
        return out

    def model(self) -> ForceModel:
        p = self.params()
        return ForceModel(
            M=max(p["M"], 1e-9),
            F_c=max(p["F_c"], 0.0),
            F_v=max(p.get("F_v", 0.0), 0.0),
            offset=p.get("offset", 0.0),
            c_drag=max(p.get("c_drag", 0.0), 0.0),
        )


def fit_idm(d: Idm, names: Sequence[str]) -> IdmFit:
    """Least-squares IDM fit with the given candidate regressors."""
    x = d.regressors(names)
    theta, *_ = np.linalg.lstsq(x, d.F, rcond=None)
    r = d.F - x @ theta
    return IdmFit(
        tuple(names), np.asarray(theta, float), float(r @ r), len(r), float(np.linalg.cond(x))
    )


def relerr(d: Idm, f: IdmFit) -> float:
    """``100 ||F - F_model|| / ||F||`` (%), as the EMPS benchmark reports it."""
    x = d.regressors(f.names)
    return 100.0 * float(np.linalg.norm(d.F - x @ f.theta) / np.linalg.norm(d.F))


def _val_sse(d: Idm, f: IdmFit) -> float:
    r = d.F - d.regressors(f.names) @ f.theta
    return float(r @ r)


def _quiet(_: str) -> None:
    return None


def diagnose_force(
    data: Series,
    validate: Series | None = None,
    progress: Callable[[str], None] = _quiet,
) -> Diagnosis:
    """Diagnose a force-input log (see module docstring): each candidate alone, then
    forward stepwise selection, then the report of the chosen inverse model."""
    est, val = (data, validate) if validate is not None else split(data)
    report = validate if validate is not None else data
    progress("inverse dynamics: filtering and differentiating")
    d_est, d_val = idm_signals(est), idm_signals(val)
    base = fit_idm(d_est, ())
    rows = _alone(d_est, d_val, base)
    current, accepted, steps, ambiguous = _stepwise(d_est, d_val, base, rows)
    d_rep = d_val if validate is not None else idm_signals(report)
    base_sum, y_base = _summary(base, d_rep, report)
    findings: list[Finding] = []
    prev = base_sum.fit_percent
    ext_sum, y_ext = base_sum, y_base
    for name, step in zip(accepted, steps[1:], strict=True):
        ext_sum, y_ext = _summary(step, d_rep, report)
        key = FORCE_CANDIDATES[name]
        findings.append(
            Finding(
                name=name,
                params={key: current.params()[key]},
                fit_percent=ext_sum.fit_percent,
                fit_gain_percent=ext_sum.fit_percent - prev,
            )
        )
        prev = ext_sum.fit_percent
    ext_sum = _summary(current, d_rep, report)[0]
    ls_json, below = _least_squares(d_est, d_rep, report, ext_sum)
    # Structure left in the force residual of the final inverse model.
    r_f = d_rep.F - d_rep.regressors(current.names) @ current.theta
    noise_f = noise_std(d_rep.F)
    wt = whiteness(r_f, d_rep.v, noise_f, max_lag=50)
    unexplained = structured(wt, noise_f, 0.01 * float(np.std(d_rep.F)))
    return Diagnosis(
        input="force",
        samples=len(data),
        baseline=base_sum,
        effects=findings,
        extended=ext_sum,
        unexplained=unexplained,
        ambiguous=ambiguous,
        candidates=[rows[n] for n in FORCE_CANDIDATES],
        notes=[
            "force input: inverse dynamic model F = M a + F_c sign(v) [+ candidates], "
            "fitted by least squares on filtered, differentiated, decimated signals "
            f"(condition number {current.cond:.3g})",
            "not candidates for a force input: " + ", ".join(NOT_APPLICABLE),
            "fit_percent: free-run speed from the measured force (viscous friction "
            "stabilises it; without it the seed's speed drifts)",
            *([below] if below else []),
        ],
        traces=Traces(
            t=report.t,
            inp=report.inp,
            y=report.v,
            y_base=y_base,
            y_ext=y_ext,
            x=report.x,
            input_name="F",
        ),
        least_squares=ls_json,
        fit_ceiling=fit_ceiling_percent([report], _best_fit(base_sum, ext_sum, ls_json)),
        residual_stats={
            "force_rms": wt.rms,
            "force_noise": wt.noise,
            "structure": wt.structure,
            "acf_outside_fraction": wt.acf_outside,
            "ccf_outside_fraction": wt.ccf_outside,
        },
    )


def _best_fit(
    base: ModelSummary, ext: ModelSummary, ls_json: dict[str, float | None] | None
) -> float:
    """The best fit (%) of the seed, the extended and the least-squares models on the
    report data: the noise ceiling is at least that."""
    ls = None if ls_json is None else ls_json.get("fit_percent")
    return max(base.fit_percent, ext.fit_percent, -np.inf if ls is None else ls)


def _least_squares(
    d_est: Idm, d_rep: Idm, report: Series, ext: ModelSummary
) -> tuple[dict[str, float | None], str | None]:
    """SysId's equation with a force input, ``F = kS sign(v) + kV v + kA a`` (kS N, kV
    N s/m, kA kg), fitted by ordinary least squares on the estimation signals with
    nothing from the configuration: the ``least_squares`` JSON object (standard errors
    from the residual, the fit of its free run on the report data), and a note when the
    extended model's fit is below it."""
    ls = fit_idm(d_est, ("viscous_friction",))
    se = np.sqrt(np.maximum(np.diag(ols_covariance(d_est.regressors(ls.names), ls.sse)), 0.0))
    fit = _summary(ls, d_rep, report)[0].fit_percent
    order = (("kS", 1), ("kV", 2), ("kA", 0))  # the columns of F_c, F_v and M
    out: dict[str, float | None] = {k: float(ls.theta[j]) for k, j in order}
    for k, j in order:
        out[f"{k}_se"] = float(se[j]) if np.isfinite(se[j]) else None
    out["fit_percent"] = fit
    below = None
    if ext.fit_percent < fit:
        below = (
            f"the extended model's free run ({ext.fit_percent:.1f} %) is below the data's "
            f"own least-squares model's ({fit:.1f} %) on the report data: its causes were "
            "chosen on the force error (inverse dynamics), not on the free run"
        )
    return out, below


def _dbic(new: IdmFit, old: IdmFit) -> float:
    return delta_bic(new.sse, old.sse, new.n, 1)


def _alone(d_est: Idm, d_val: Idm, base: IdmFit) -> dict[str, CandidateRow]:
    """Each candidate fitted alone on top of the seed: its row of the table."""
    base_val = _val_sse(d_val, base)
    tried = {n: fit_idm(d_est, (n,)) for n in FORCE_CANDIDATES}
    rows: dict[str, CandidateRow] = {}
    for n, f in tried.items():
        vs = _val_sse(d_val, f)
        physical = n == "load_force" or f.theta[2] > 0.0
        ok = physical and passes(_dbic(f, base), vs, base_val)
        rows[n] = CandidateRow(
            name=n,
            params={FORCE_CANDIDATES[n]: float(f.theta[2])},
            fit_percent=100.0 - relerr(d_val, f),
            gain_percent=relerr(d_val, base) - relerr(d_val, f),
            cost_ratio=vs / base_val,
            delta_bic=_dbic(f, base),
            accepted=False,
            note="passes alone" if ok else ("" if physical else "unphysical sign"),
        )
    return rows


def _stepwise(
    d_est: Idm, d_val: Idm, base: IdmFit, rows: dict[str, CandidateRow]
) -> tuple[IdmFit, list[str], list[IdmFit], list[tuple[str, str]]]:
    """Forward stepwise: each round adds the candidate that lowers the validation error
    most, if it passes both tests against the current model.  Returns the final model,
    the accepted names in order, the model after each step (the seed first) and the
    ambiguous pairs; updates the notes of ``rows``."""
    current, cur_val = base, _val_sse(d_val, base)
    accepted: list[str] = []
    steps = [base]
    ambiguous: list[tuple[str, str]] = []
    # Every candidate of a physical sign alone competes in each round, not only those that
    # pass alone: an offset hidden under viscous friction passes only on top of it.
    remaining = [n for n in FORCE_CANDIDATES if rows[n].note != "unphysical sign"]
    while remaining:
        trials = {n: fit_idm(d_est, (*accepted, n)) for n in remaining}
        scored = sorted(remaining, key=lambda n: _val_sse(d_val, trials[n]))
        best = scored[0]
        f = trials[best]
        vs = _val_sse(d_val, f)
        physical = all(f.theta[2 + k] > 0.0 for k, n in enumerate(f.names) if n != "load_force")
        if not (physical and passes(_dbic(f, current), vs, cur_val)):
            for n in remaining:
                if rows[n].note == "passes alone":
                    rows[n] = _note(rows[n], "adds nothing once others are in")
            break
        for n in scored[1:]:
            if close(_val_sse(d_val, trials[n]), vs, absolute=0.0):
                ambiguous.append((best, n))
                rows[n] = _note(rows[n], f"ambiguous with {best}")
        accepted.append(best)
        rows[best] = _note(rows[best], "accepted", True)
        current, cur_val = f, vs
        steps.append(f)
        remaining = [n for n in remaining if n != best and not rows[n].note.startswith("amb")]
    return current, accepted, steps, ambiguous


def _note(row: CandidateRow, note: str, accepted: bool = False) -> CandidateRow:
    from dataclasses import replace

    return replace(row, note=note, accepted=accepted or row.accepted)


def _summary(f: IdmFit, d: Idm, report: Series) -> tuple[ModelSummary, Array]:
    """Free-run speed fit on the report data and force error of the IDM."""
    v_sim, _ = simulate_force(f.model(), report.t, report.inp, initial_speed(report.v))
    v_sim = np.where(np.isfinite(v_sim), v_sim, 0.0)
    return (
        ModelSummary(
            fit_percent=fit_percent(report.v, v_sim),
            rmse=rmse(report.v, v_sim),
            params=f.params(),
            force_relerr_percent=relerr(d, f),
        ),
        v_sim,
    )
