"""What a free run of a voltage-input log returns (:mod:`truckd.ident.fastsim` computes it):
the speeds and position at each sample, the current and driver voltage when read, and the
stiction torques that would give the same run.  Pure data, no I/O."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass(frozen=True)
class StictionBand:
    """The stiction torques ``K_stiction`` (N m) that give a free run exactly, the rest of
    the model held: those whose breakaway threshold ``kappa K_stiction / J_S`` (what the
    run computes, per unit inertia) lies in ``[stuck, moved)``.  Every stick-or-break
    decision of the run goes the same way for them (the threshold enters nothing else).
    Sufficient, not necessary: a torque outside may give the same run (a drive that breaks
    away against a larger Coulomb friction stops at once, as a stuck one)."""

    stuck: float
    """The largest net drive (per unit inertia) at which the run stayed stuck."""
    moved: float
    """The smallest net drive at which it broke away."""
    kappa: float
    J_S: float

    def holds(self, k_stiction: float) -> bool:
        """Whether ``k_stiction`` (N m) gives the same run."""
        sigma = self.kappa * k_stiction / self.J_S
        return self.stuck <= sigma < self.moved


@dataclass(frozen=True)
class VoltagePrediction:
    """Free-run prediction of a voltage-input log (SI).

    The current and the driver voltage at each sample are computed when first read
    (a speed-only fit never reads them)."""

    v: Array
    """Speed as the sensor reports it (m/s)."""
    rotor_speed: Array
    """The motor's true speed (rad/s)."""
    rotor_angle: Array
    """The motor's angle from the start (rad)."""
    ratio: float
    """Travel per motor radian (m/rad)."""
    sampled: Callable[[], tuple[Array, Array]] = field(repr=False, compare=False)
    """Computes ``(i, volts)``: the run's current and driver voltage at each sample."""
    stiction: StictionBand | None = field(default=None, repr=False, compare=False)
    """The breakaway torques that give this same run (None: not known)."""

    @cached_property
    def v_true(self) -> Array:
        """True speed (m/s), computed when first read (a fit reads ``v`` only)."""
        return self.rotor_speed * self.ratio

    @cached_property
    def x(self) -> Array:
        """Position (m), computed when first read."""
        return self.rotor_angle * self.ratio

    @cached_property
    def _at_samples(self) -> tuple[Array, Array]:
        # As simulate_voltage runs: absurd trial parameters overflow silently.
        with np.errstate(over="ignore", invalid="ignore"):
            return self.sampled()

    @property
    def i(self) -> Array:
        """Quasi-static motor current at each sample (A)."""
        return self._at_samples[0]

    @property
    def volts(self) -> Array:
        """Open-circuit driver voltage active at each sample (V)."""
        return self._at_samples[1]
