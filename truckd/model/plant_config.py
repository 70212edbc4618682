"""The ``plant:`` section of truck.yaml: the simulated truck's effects and sensor
imperfections.  Here, beside the model, and not in :mod:`truckd.sim`, because the
configuration (which the daemon on the car loads) names it, while the car never loads the
simulator."""

from __future__ import annotations

from dataclasses import dataclass

from truckd.model.effects import Effects
from truckd.schema import spec


@dataclass(frozen=True)
class PlantConfig:
    """The simulated truck's effects and sensor imperfections."""

    effects: Effects = spec("effects the seed model lacks", default_factory=Effects)
    noise_v: float = spec("speed measurement noise (std)", unit="m/s", lo=0.0, hi=10.0, default=0.0)
    noise_i: float = spec(
        "current measurement noise (std)", unit="A", lo=0.0, hi=100.0, default=0.0
    )
    encoder_ticks_per_rev: int = spec(
        "encoder ticks per wheel revolution, 0 = ideal speed sensor",
        lo=0,
        hi=1_000_000,
        default=0,
    )
    seed: int = spec("random seed of the sensor noise", lo=0, default=0)


def encoder_ticks_per_rev(plant_ticks: int, link_ticks: int) -> int:
    """Ticks per wheel revolution both sides use: the plant's encoder when it models one
    (``plant.encoder_ticks_per_rev`` > 0), else the link configuration's."""
    return plant_ticks if plant_ticks > 0 else link_ticks
