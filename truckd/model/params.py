"""Vehicle parameters: the seed's symbols, SI units, validated on load.

Friction torques and inertia are referred to the motor shaft.  Vehicle speed is
``v = r_w * omega_m / (n_g * n_fd)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

from truckd.schema import spec


@dataclass(frozen=True)
class VehicleParams:
    """Motor, drivetrain and friction parameters of one truck (all SI)."""

    R_m: float = spec("armature resistance", unit="ohm", lo=0.0, lo_open=True, hi=100.0)
    L_m: float = spec("armature inductance", unit="H", lo=0.0, lo_open=True, hi=1.0)
    K_v: float = spec("back-EMF constant", unit="V s/rad", lo=0.0, lo_open=True, hi=10.0)
    K_T: float = spec("torque constant", unit="N m/A", lo=0.0, lo_open=True, hi=10.0)
    J_S: float = spec(
        "total inertia reflected to the motor shaft", unit="kg m^2", lo=0.0, lo_open=True, hi=10.0
    )
    n_g: float = spec("gearbox ratio (motor turns per output turn)", lo=0.0, lo_open=True, hi=1e3)
    n_fd: float = spec("final drive ratio", lo=0.0, lo_open=True, hi=1e3)
    r_w: float = spec("wheel radius", unit="m", lo=0.0, lo_open=True, hi=2.0)
    m: float = spec(
        "vehicle mass: the weight that bounds a load or drag an effect may have (the "
        "inertia the dynamics use is J_S)",
        unit="kg",
        lo=0.0,
        lo_open=True,
        hi=1e4,
    )
    K_coulomb: float = spec(
        "Coulomb friction torque at the motor shaft", unit="N m", lo=0.0, hi=100.0
    )
    K_stiction: float = spec(
        "static (breakaway) friction torque at the motor shaft", unit="N m", lo=0.0, hi=100.0
    )
    V_batt: float = spec(
        "nominal battery voltage: the driver's output limit",
        unit="V",
        lo=0.0,
        lo_open=True,
        hi=100.0,
        default=7.2,
    )

    def validate(self) -> str | None:
        """Cross-field checks; a message when the set is not physical.

        Besides the friction order, the motor's two time constants and its top speed must
        be those of a machine (each parameter alone only has to be positive): the
        electrical ``L_m / R_m`` within [1e-7, 10] s, the mechanical ``J_S R_m / (K_T
        K_v)`` within [1e-5, 1e4] s, the no-load speed ``V_batt / K_v`` at the wheels within
        [1e-4, 1000] m/s.  Beyond them the controller's Riccati equation and the simulation
        overflow or lose every digit (a value of 1e-300 passed the positive check)."""
        if self.K_stiction < self.K_coulomb:
            return (
                f"K_stiction ({self.K_stiction}) must be >= K_coulomb ({self.K_coulomb}): "
                "breakaway friction is never below sliding friction"
            )
        tau_e = self.L_m / self.R_m
        if not 1e-7 <= tau_e <= 10.0:
            return (
                f"L_m / R_m = {tau_e:.3g} s: the electrical time constant of a motor lies "
                "within [1e-7, 10] s"
            )
        tau_m = self.mechanical_time_constant
        if not 1e-5 <= tau_m <= 1e4:
            return (
                f"J_S R_m / (K_T K_v) = {tau_m:.3g} s: the mechanical time constant of a "
                "motor and its load lies within [1e-5, 1e4] s"
            )
        v_top = self.V_batt / self.K_v * self.r_w / (self.n_g * self.n_fd)
        if not 1e-4 <= v_top <= 1e3:
            return (
                f"V_batt / K_v r_w / (n_g n_fd) = {v_top:.3g} m/s: the no-load speed at the "
                "wheels lies within [1e-4, 1000] m/s"
            )
        return None

    @cached_property
    def mechanical_time_constant(self) -> float:
        """The motor and its load's mechanical time constant ``J_S R_m / (K_T K_v)``, s."""
        return self.J_S * self.R_m / (self.K_T * self.K_v)

    @cached_property
    def ratio(self) -> float:
        """Speed per motor speed, ``r_w / (n_g n_fd)``, m/rad."""
        return self.r_w / (self.n_g * self.n_fd)

    def stall_acceleration(self, u: float) -> float:
        """The vehicle's acceleration (m/s^2) from rest under ``u`` volts before friction:
        the stall torque ``K_T u / R_m`` on the inertia ``J_S``, at the wheels."""
        return self.K_T * u / (self.R_m * self.J_S) * self.ratio

    def speed(self, omega_m: float) -> float:
        """Vehicle speed (m/s) from motor speed (rad/s)."""
        return omega_m * self.ratio

    def omega(self, v: float) -> float:
        """Motor speed (rad/s) from vehicle speed (m/s)."""
        return v / self.ratio

    def force_to_torque(self, force: float) -> float:
        """A force at the wheels (N) as torque at the motor shaft (N m)."""
        return force * self.ratio

    def replace(self, **changes: float) -> VehicleParams:
        """A copy with some parameters changed."""
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, float]:
        """The parameters keyed by the seed's symbols."""
        return {f.name: float(getattr(self, f.name)) for f in dataclasses.fields(self)}
