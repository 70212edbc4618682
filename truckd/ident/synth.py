"""Synthetic logs for tests and benchmarks: random excitation through the simulated plant.

The logs come from :func:`truckd.sim.plant.simulate_open_loop` (the reference plant,
not the fitting loop's simulator), with random command levels held for random times,
random effect magnitudes in ranges where the effect is visible, and sensor noise.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numpy.typing import NDArray

from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams
from truckd.sim.plant import PlantConfig, simulate_open_loop

Array = NDArray[np.float64]

EFFECT_RANGES: dict[str, tuple[float, float]] = {
    "viscous_friction": (3e-5, 1e-4),  # N m s/rad (back-EMF damping is ~1e-4)
    "aero_drag": (0.8, 2.5),  # N/(m/s)^2
    "load_force": (2.0, 6.0),  # N, either sign
    "input_delay": (0.012, 0.08),  # s, not a multiple of the 10 ms sample
    "dead_zone": (0.8, 2.0),  # V
    "voltage_saturation": (3.5, 5.5),  # V
    "battery_sag": (0.08, 0.25),  # ohm
    "sensor_lag": (0.03, 0.15),  # s
}
"""Ranges of the random magnitudes the tests and the benchmark draw from."""


def random_effect(name: str, rng: np.random.Generator) -> float:
    """A random magnitude of one effect (random sign for load_force)."""
    lo, hi = EFFECT_RANGES[name]
    val = float(rng.uniform(lo, hi))
    if name == "load_force" and rng.random() < 0.5:
        val = -val
    return val


def excitation(
    rng: np.random.Generator, n: int, h: float = 0.01, u_max: float = 7.0
) -> tuple[Array, Array]:
    """``(t, u)``: random levels in ``[-u_max, u_max]`` (some zero) held 0.2-2 s.

    The sample time jitters by up to 2 % so that nothing relies on an exact grid.
    """
    dt = h * (1.0 + 0.02 * rng.uniform(-1.0, 1.0, n - 1))
    t = np.concatenate([[0.0], np.cumsum(dt)])
    u = np.zeros(n)
    k = 0
    while k < n:
        length = int(rng.integers(int(0.2 / h), int(2.0 / h)))
        u[k : k + length] = 0.0 if rng.random() < 0.15 else rng.uniform(-u_max, u_max)
        k += length
    return t, u


def plant_log(
    p: VehicleParams,
    effects: Effects,
    seed: int,
    n: int = 6000,
    noise_v: float = 0.01,
    noise_i: float = 0.3,
    with_current: bool = True,
) -> Log:
    """A log of the simulated plant under random excitation (columns t, u, v[, i], x)."""
    rng = np.random.default_rng(seed)
    t, u = excitation(rng, n)
    cfg = PlantConfig(effects=effects, noise_v=noise_v, noise_i=noise_i, seed=seed)
    sim = simulate_open_loop(p, t, u, cfg)
    cols: dict[str, Array] = {"t": t, "u": u, "v": sim.v}
    if with_current:
        cols["i"] = sim.i
    return Log(cols, f"<plant seed {seed}: {', '.join(effects.active()) or 'no effect'}>")


def with_effect(name: str, value: float) -> Effects:
    """Effects with one switched on."""
    return dataclasses.replace(Effects(), **{name: value})
