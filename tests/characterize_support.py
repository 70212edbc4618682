"""Drawn trucks for the `truckd characterize` tests and benchmark: a simulated truck that is
not the configured one (motor constant and mass off by 2-5x) with one hidden effect, and
the feedforward constants its parameters imply."""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Any

from truckd.model.params import VehicleParams

EFFECT_RANGES: dict[str, tuple[float, float]] = {
    "load_force": (0.5, 0.9),  # of the sliding friction force: a slope it stops on at 0 V
    "dead_zone": (1.0, 1.5),  # V
    "battery_sag": (0.2, 0.3),  # ohm
    "input_delay": (0.06, 0.1),  # s
}
"""Hidden effects and the range each is drawn from (sizes a driver, a battery, a link, a
slope or a trailer really show on a 1:14 truck; the load as a share of the sliding
friction force, so that the truck, rolling at 0 V, comes to rest)."""


@dataclass(frozen=True)
class DrawnTruck:
    """The plant's ``plant.vehicle`` keys, its hidden effect and value."""

    vehicle: dict[str, float]
    effect: str
    value: float
    motor_factor: float
    mass_factor: float

    def params(self, configured: VehicleParams) -> VehicleParams:
        return configured.replace(**self.vehicle)

    def plant_section(self) -> dict[str, Any]:
        return {"vehicle": self.vehicle, "effects": {self.effect: self.value}}


def draw_truck(seed: int, configured: VehicleParams, effect: str | None = None) -> DrawnTruck:
    """Motor constant (K_v = K_T) 2-3.5x and mass (m, J_S) 2-5x the configured one's, the
    mechanical time constant kept within 0.06-0.3 s (the 100 Hz loop sees it, the track
    holds the steps); ``effect`` (default: drawn) of a size from :data:`EFFECT_RANGES`."""
    rng = random.Random(seed)
    p = configured
    tau0 = p.J_S * p.R_m / (p.K_T * p.K_v)
    while True:
        fk, fm = rng.uniform(2.0, 3.5), rng.uniform(2.0, 5.0)
        if 0.06 <= tau0 * fm / (fk * fk) <= 0.3:
            break
    name = effect if effect is not None else rng.choice(sorted(EFFECT_RANGES))
    lo, hi = EFFECT_RANGES[name]
    vehicle = {"K_v": p.K_v * fk, "K_T": p.K_T * fk, "J_S": p.J_S * fm, "m": p.m * fm}
    value = rng.uniform(lo, hi)
    if name == "load_force":  # N: a slope (or a trailer) the truck still stops on at 0 V
        value *= p.K_coulomb / p.ratio
    return DrawnTruck(vehicle, name, value, fk, fm)


def feedforward(p: VehicleParams) -> dict[str, float]:
    """SysId's kS (V), kV (V s/m), kA (V s^2/m) of the seed model with parameters ``p``."""
    r = p.r_w / (p.n_g * p.n_fd)
    return {
        "kS": p.R_m * p.K_coulomb / p.K_T,
        "kV": p.K_v / r,
        "kA": p.R_m * p.J_S / (p.K_T * r),
    }


CHARACTERIZE_FOR_DRAWN = {"step_voltages": [2.0, 4.0], "quasistatic_ramp_v_per_s": 1.4}
"""The ``characterize:`` section for the drawn trucks: their motor constant is 2-3.5x the
configured one, so they need more voltage for the same speed (a user sets this too)."""
