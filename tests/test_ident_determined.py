"""What the data determine: the Fisher information of the seed's simulation-error fit
(``seed.fisher_rel_se``) where a constant sits at its zero bound."""

from __future__ import annotations

import numpy as np

from truckd.config.truck import load_config
from truckd.ident.data import Series, series_from_log
from truckd.ident.seed import DETERMINED, fisher_rel_se
from truckd.ident.voltage import FitResult, Weights, residuals, seed_params
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

NOISE = 0.01
"""Speed noise of the simulated logs (m/s)."""


def _runs(p: VehicleParams, kind: str) -> list[Series]:
    """A forward and a backward run of a drivetrain with no Coulomb friction: SysId's
    quasi-static ramps (0.4 V/s from rest, 12 s) or its dynamic steps (4 V, 3 s)."""
    out = []
    for k, sign in enumerate((1.0, -1.0)):
        t = np.arange(0.0, 12.0 if kind == "ramps" else 3.0, 0.005)
        u = sign * (0.4 * t if kind == "ramps" else np.where(t > 0.2, 4.0, 0.0))
        sim = simulate_open_loop(p, t, u, PlantConfig(noise_v=NOISE, seed=11 + k))
        out.append(series_from_log(Log({"t": t, "u": u, "v": sim.v, "x": sim.x}, kind)))
    return out


def test_slow_symmetric_ramps_do_not_determine_ka_with_friction_at_zero() -> None:
    """On symmetric slow ramps kS sign(v) and kA a are nearly the same column (the
    acceleration is constant on each ramp): with the Coulomb friction at its zero bound,
    a step relative to its value moved nothing and the information called kA determined
    (a shooter's ramps: kA 6 %, nine times SysId's kA; here 8 %, and kS of 1e-9 to
    0.02 %). The same light flywheel's steps do determine it."""
    p0 = load_config().vehicle
    p = p0.replace(K_coulomb=1e-9, K_stiction=1e-9, J_S=0.1 * p0.J_S)
    free = seed_params(p, with_current=False)
    w = Weights(1.0 / NOISE)
    rel = {}
    for kind in ("ramps", "steps"):
        data = _runs(p, kind)
        r = residuals(p, Effects(), data, w)
        got = fisher_rel_se(FitResult(p, Effects(), float(r @ r), len(r), 0), free, data, w)
        assert got is not None
        rel[kind] = got
    ks, kv, ka = rel["ramps"]
    assert ks == float("inf")  # at zero: no relative error to speak of
    assert kv < DETERMINED
    assert ka > DETERMINED, rel
    assert rel["steps"][1] < DETERMINED and rel["steps"][2] < DETERMINED, rel
