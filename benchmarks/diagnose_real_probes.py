"""What the ramps of a real SysId log can and cannot tell about the steps (probes).

For each SysId ``FILE.json`` (quasi-static ramps fitted, dynamic steps validated, as
``benchmarks/diagnose_real.py`` does), three measurements outside the diagnosis, with
SysId's first-order model ``V = kS sgn v + kV v + kA a`` simulated free-run from each
run's measured start (exact per row, Coulomb friction, the truck sticking at zero speed
while ``|V| <= kS``, a reversal stopping at zero for the rest of its row) and scored at
the fresh speed readings as ``fit_percent`` is:

* ``speed_lag_s``: how far the logged speed lags the logged position, per run: the
  least-squares ``tau`` of ``x - x0 - integral(v) = tau v + c`` over the samples above a
  tenth of the run's top speed (a speed delayed by ``tau``, or low-pass filtered with
  time constant ``tau``, falls behind its position by ``tau v``); with its standard error.
* ``ka_scan``: for each kA of a grid, kS and kV refitted by simulation error on the
  ramps; the ramps' cost (sum of squared speed errors, m^2/s^2) and the steps' fit, without
  and with a first-order speed-sensor lag equal to the ramps' median ``speed_lag_s``.
* ``supply``: each step's mean speed over its last second against the ramps' straight
  line ``|V| = kS + kV |v|`` (OLS on the ramps above a tenth of the top speed): the
  voltage that line needs for that speed, beside the logged command; and the steps'
  fit with the commands clipped to it (an upper bound: the clip is read off the
  validation data).

    nice .venv/bin/python benchmarks/diagnose_real_probes.py FILE.json [FILE.json ...]
        [--json FILE --key NAME]
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from results import machine, write_json
from scipy.optimize import least_squares

from truckd.ident.data import fresh_mask
from truckd.ident.sysid import read_sysid

Array = NDArray[np.float64]
RAMPS = "slow-forward,slow-backward"
STEPS = "fast-forward,fast-backward"
KA_GRID = (0.25, 0.5, 1.0, 2.0, 4.0)
"""kA of the scan, as multiples of the ramps' own free-run optimum."""


@dataclass(frozen=True)
class Run:
    """One SysId test in SI: time (s), voltage (V), position, speed, fresh readings."""

    name: str
    t: Array
    u: Array
    x: Array
    v: Array
    fresh: NDArray[np.bool_]


def runs_of(path: str, tests: str) -> list[Run]:
    """The selected tests of a SysId file (``truckd.ident.sysid``'s reading)."""
    out = []
    for log in read_sysid(f"{path}:{tests}"):
        c = log.columns
        v = np.asarray(c["v"], float)
        out.append(
            Run(log.source, c["t"] - c["t"][0], c["u"], c["x"] - c["x"][0], v, fresh_mask(v))
        )
    return out


def speed_lag(r: Run) -> tuple[float, float]:
    """``tau`` (s) and its standard error: ``x - integral(v) = tau v + c``."""
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (r.v[1:] + r.v[:-1]) * np.diff(r.t))])
    keep = r.fresh & (np.abs(r.v) > 0.1 * float(np.max(np.abs(r.v))))
    a = np.column_stack([r.v[keep], np.ones(int(keep.sum()))])
    y = (r.x - integral)[keep]
    sol, *_ = np.linalg.lstsq(a, y, rcond=None)
    res = y - a @ sol
    cov = float(res @ res) / max(len(y) - 2, 1) * np.linalg.inv(a.T @ a)
    return float(sol[0]), float(np.sqrt(cov[0, 0]))


def simulate(r: Run, ks: float, kv: float, ka: float, lag: float, u: Array | None = None) -> Array:
    """Speed the sensor reports: first-order model, row by row (each row's voltage held
    to the next row), then a first-order sensor lag ``lag`` s (0: none)."""
    u = r.u if u is None else u
    tau = ka / kv
    n = len(r.t)
    out = np.empty(n)
    w = float(r.v[0])
    out[0] = w
    for k in range(n - 1):
        h = float(r.t[k + 1] - r.t[k])
        uk = float(u[k])
        if w == 0.0 and abs(uk) <= ks:
            out[k + 1] = 0.0
            continue
        s = math.copysign(1.0, w if w != 0.0 else uk)
        target = (uk - s * ks) / kv
        nxt = target + (w - target) * math.exp(-h / tau)
        w = 0.0 if (w != 0.0 and nxt * w < 0.0) else nxt
        out[k + 1] = w
    if lag <= 0.0:
        return out
    seen = np.empty(n)
    f = out[0]
    seen[0] = f
    for k in range(1, n):
        f += (1.0 - math.exp(-float(r.t[k] - r.t[k - 1]) / lag)) * (out[k] - f)
        seen[k] = f
    return seen


def errors(runs: list[Run], ks: float, kv: float, ka: float, lag: float) -> Array:
    """Simulated minus logged speed at the fresh readings, all runs end to end."""
    return np.concatenate([(simulate(r, ks, kv, ka, lag) - r.v)[r.fresh] for r in runs])


def fit_percent(runs: list[Run], ks: float, kv: float, ka: float, lag: float) -> float:
    """``100 (1 - ||y - y_sim|| / ||y - mean y||)`` at the fresh readings."""
    y = np.concatenate([r.v[r.fresh] for r in runs])
    e = errors(runs, ks, kv, ka, lag)
    return 100.0 * (1.0 - float(np.linalg.norm(e)) / float(np.linalg.norm(y - y.mean())))


def refit(runs: list[Run], ka: float | None, lag: float, start: Array) -> Array:
    """(kS, kV, kA) by simulation error on ``runs``; kA held when given."""

    def res(th: Array) -> Array:
        return errors(runs, th[0], th[1], ka if ka is not None else th[2], lag)

    x0 = start[:2] if ka is not None else start
    low = np.array([-np.inf, 1e-9, 1e-9])[: len(x0)]
    sol = least_squares(res, x0, bounds=(low, np.inf), x_scale=np.abs(x0) + 1e-3, max_nfev=60)
    return np.array([sol.x[0], sol.x[1], ka if ka is not None else sol.x[2]])


def ramp_line(ramps: list[Run]) -> tuple[float, float]:
    """kS, kV of ``|V| = kS + kV |v|`` on the ramps (above a tenth of the top speed)."""
    v = np.concatenate([np.abs(r.v[r.fresh]) for r in ramps])
    u = np.concatenate([np.abs(r.u[r.fresh]) for r in ramps])
    keep = v > 0.1 * float(v.max())
    kv, ks = np.polyfit(v[keep], u[keep], 1)
    return float(ks), float(kv)


def probe(path: str) -> dict[str, Any]:
    """The three probes of one SysId file."""
    ramps, steps = runs_of(path, RAMPS), runs_of(path, STEPS)
    lags = {r.name.rsplit(":", 1)[1]: speed_lag(r) for r in (*ramps, *steps)}
    lag = float(np.median([lags[r.name.rsplit(":", 1)[1]][0] for r in ramps]))
    ks0, kv0 = ramp_line(ramps)
    best = refit(ramps, None, 0.0, np.array([ks0, kv0, 0.1 * kv0]))
    ks, kv, ka = (float(b) for b in best)
    scan = []
    for m in KA_GRID:
        ka_m = ka * m
        row: dict[str, Any] = {"kA": ka_m}
        for name, sensor in (("no_lag", 0.0), ("measured_lag", max(lag, 0.0))):
            th = refit(ramps, ka_m, sensor, best)
            e = errors(ramps, th[0], th[1], ka_m, sensor)
            row[name] = {
                "kS": float(th[0]),
                "kV": float(th[1]),
                "ramp_cost": float(e @ e),
                "step_fit_percent": fit_percent(steps, th[0], th[1], ka_m, sensor),
            }
        scan.append(row)
    supply: list[dict[str, Any]] = []
    clip: list[float] = []
    for r in steps:
        last = r.fresh & (r.t > r.t[-1] - 1.0)
        speed = float(np.mean(np.abs(r.v[last])))
        clip.append(ks0 + kv0 * speed)
        supply.append(
            {
                "test": r.name.rsplit(":", 1)[1],
                "command_V": float(np.mean(np.abs(r.u[last]))),
                "ramp_line_V": clip[-1],
            }
        )
    clipped = [
        Run(r.name, r.t, np.clip(r.u, -c, c), r.x, r.v, r.fresh)
        for r, c in zip(steps, clip, strict=True)
    ]
    return {
        "file": path,
        "speed_lag_s": {k: {"tau": v[0], "se": v[1]} for k, v in lags.items()},
        "ramps_free_run_optimum": {"kS": ks, "kV": kv, "kA": ka},
        "ka_scan": scan,
        "supply": supply,
        "ramp_line": {"kS": ks0, "kV": kv0},
        "step_fit_clipped_at_ramp_line_V": fit_percent(clipped, ks, kv, ka, 0.0),
        "step_fit_ramps_optimum": fit_percent(steps, ks, kv, ka, 0.0),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", help="SysId FILE.json")
    ap.add_argument("--json", metavar="FILE", help="store the rows (benchmarks/results.py)")
    ap.add_argument("--key", help="the measurement's name, what_YYYY-MM-DD")
    args = ap.parse_args()
    rows = []
    for path in args.files:
        p = probe(path)
        rows.append(p)
        print(path)
        for k, v in p["speed_lag_s"].items():
            print(f"  speed lags position, {k}: {1e3 * v['tau']:.1f} +- {1e3 * v['se']:.1f} ms")
        for row in p["ka_scan"]:
            a, b = row["no_lag"], row["measured_lag"]
            print(
                f"  kA {row['kA']:.4g}: ramp cost {a['ramp_cost']:.4g} "
                f"steps {a['step_fit_percent']:.1f} % | with lag: {b['ramp_cost']:.4g} "
                f"{b['step_fit_percent']:.1f} %"
            )
        for s in p["supply"]:
            print(
                f"  {s['test']}: command {s['command_V']:.2f} V, ramp line {s['ramp_line_V']:.2f} V"
            )
        print(
            f"  steps: ramps' optimum {p['step_fit_ramps_optimum']:.1f} %, commands clipped "
            f"at the ramp line {p['step_fit_clipped_at_ramp_line_V']:.1f} %"
        )
    if args.json:
        write_json(args.json, {"machine": machine(), "rows": rows}, args.key)
    return 0


if __name__ == "__main__":
    sys.exit(main())
