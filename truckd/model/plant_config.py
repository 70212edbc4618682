"""The ``plant:`` section of truck.yaml: the simulated truck's effects, sensor
imperfections, its own vehicle parameters where they differ from the configured ones, and
how its firmware is wired.  Here, beside the model, and not in :mod:`truckd.sim`, because
the configuration (which the daemon on the car loads) names it, while the car never loads
the simulator."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.schema import spec


def _opt(doc: str, unit: str = "", positive: bool = True) -> float | None:
    """An optional vehicle parameter of the plant: absent (None) means the configured one."""
    field: float | None = spec(
        doc + " (absent: the configured vehicle's)", unit=unit, lo=0.0, lo_open=positive,
        default=None,
    )  # fmt: skip
    return field


@dataclass(frozen=True)
class PlantVehicle:
    """The simulated truck's vehicle parameters where they differ from ``vehicle:``: any
    subset of its keys; the rest are the configured truck's.  So a test, a user or the HIL
    harness can hand the controller a truck it does not know."""

    R_m: float | None = _opt("armature resistance", "ohm")
    L_m: float | None = _opt("armature inductance", "H")
    K_v: float | None = _opt("back-EMF constant", "V s/rad")
    K_T: float | None = _opt("torque constant", "N m/A")
    J_S: float | None = _opt("total inertia reflected to the motor shaft", "kg m^2")
    n_g: float | None = _opt("gearbox ratio")
    n_fd: float | None = _opt("final drive ratio")
    r_w: float | None = _opt("wheel radius", "m")
    m: float | None = _opt("vehicle mass", "kg")
    K_coulomb: float | None = _opt(
        "Coulomb friction torque at the motor shaft", "N m", positive=False
    )
    K_stiction: float | None = _opt(
        "static friction torque at the motor shaft", "N m", positive=False
    )
    V_batt: float | None = _opt("battery voltage", "V")

    def given(self) -> dict[str, float]:
        """The keys set, with their values."""
        return {
            f.name: float(v)
            for f in dataclasses.fields(self)
            if (v := getattr(self, f.name)) is not None
        }

    def over(self, configured: VehicleParams) -> VehicleParams:
        """The plant's parameters: ``configured`` with the keys set here replaced."""
        return dataclasses.replace(configured, **self.given())


@dataclass(frozen=True)
class Wiring:
    """How the simulated firmware is wired to its motor and encoder (a real truck can be
    wired the wrong way round: the bring-up checks of ``truckd characterize`` find it)."""

    motor_sign: int = spec("1, or -1: the motor leads swapped", lo=-1, hi=1, default=1)
    encoder_sign: int = spec(
        "1, or -1: the encoder counts down going forward", lo=-1, hi=1, default=1
    )
    counts_scale: float = spec(
        "encoder counts per metre as a multiple of the configured ones (2: a 2x encoder)",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=1.0,
    )

    def validate(self) -> str | None:
        for name in ("motor_sign", "encoder_sign"):
            if getattr(self, name) == 0:
                return f"{name} must be 1 or -1, not 0"
        return None


@dataclass(frozen=True)
class PlantConfig:
    """The simulated truck's effects and sensor imperfections."""

    effects: Effects = spec("effects the seed model lacks", default_factory=Effects)
    noise_v: float = spec(
        "speed measurement noise (std) of open-loop logs (truckd simulate, synthetic logs); "
        "the closed loop measures the speed by the encoder (encoder_ticks_per_rev)",
        unit="m/s",
        lo=0.0,
        hi=10.0,
        default=0.0,
    )
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
    vehicle: PlantVehicle = spec(
        "the simulated truck's vehicle parameters where they differ from vehicle:",
        default_factory=PlantVehicle,
    )
    wiring: Wiring = spec(
        "the simulated firmware's wiring (motor and encoder sign, counts scale)",
        default_factory=Wiring,
    )


def encoder_ticks_per_rev(plant_ticks: int, link_ticks: int) -> int:
    """Ticks per wheel revolution both sides use: the plant's encoder when it models one
    (``plant.encoder_ticks_per_rev`` > 0), else the link's."""
    return plant_ticks if plant_ticks > 0 else link_ticks
