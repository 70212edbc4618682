"""Synthetic logs for tests and benchmarks: random excitation through the simulated plant.

The logs come from :func:`truckd.sim.plant.simulate_open_loop` (the reference plant,
not the fitting loop's simulator), with random command levels held for random times,
random effect magnitudes in ranges where the effect is visible, and sensor noise.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

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
    "dead_zone_offset": (0.8, 2.0),  # V
    "voltage_saturation": (3.5, 5.5),  # V
    "battery_sag": (0.08, 0.25),  # ohm
    "sensor_lag": (0.03, 0.15),  # s
    "current_limit": (20.0, 45.0),  # A (the default motor's stall current is 85 A)
    "backlash": (1.0, 4.0),  # rad at the motor shaft (2-8 degrees at the wheel)
    "stribeck": (0.006, 0.015),  # N m above K_coulomb (0.015) at zero speed
    "resistance_drift": (0.6, 1.5),  # K/W: 30-120 K over a log of random steps
}
"""Ranges of the random magnitudes the tests and the benchmark draw from."""

COMPANION_RANGES: dict[str, tuple[str, float, float]] = {
    "stribeck": ("stribeck_speed", 0.05, 0.3),  # m/s
    "resistance_drift": ("winding_time_constant", 10.0, 40.0),  # s
}
"""The second parameter drawn with an effect that has one (name, range)."""


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


def random_effects(name: str, rng: np.random.Generator, k_scale: float = 1.0) -> Effects:
    """Effects with ``name`` switched on at a random magnitude (scaled for a truck whose
    motor constant is ``k_scale`` times the default, :func:`scaled_effect`), and its
    companion parameter (:data:`COMPANION_RANGES`) drawn too."""
    values = {name: scaled_effect(name, random_effect(name, rng), k_scale)}
    if name in COMPANION_RANGES:
        other, lo, hi = COMPANION_RANGES[name]
        values[other] = scaled_effect(other, float(rng.uniform(lo, hi)), k_scale)
    return dataclasses.replace(Effects(), **values)


SCALE_RANGE = (0.1, 10.0)
"""Motor constant and inertia of drawn trucks: this factor times the default, log-uniform."""


@dataclass(frozen=True)
class DrawnTruck:
    """A truck unlike the configured one, and how its log is recorded."""

    params: VehicleParams
    k_scale: float
    """Motor constant (K_v, K_T and the friction torques) relative to the default."""
    j_scale: float
    """Inertia J_S relative to the default."""
    rate_hz: float
    jitter: float
    """Relative jitter of the sample time."""
    drop: float
    """Fraction of rows dropped (a logger that misses samples)."""
    speed_step: float
    """Resolution of the logged speed, m/s (coarse steps)."""
    noise_v: float


def draw_truck(p: VehicleParams, rng: np.random.Generator) -> DrawnTruck:
    """A truck with 0.1x..10x the default motor constant and inertia, logged at 50-200 Hz
    with jittered timing, dropped rows and coarse speed steps.

    The friction torques scale with the motor constant (the breakaway voltage stays);
    the speed noise and resolution scale with the truck's top speed (the same sensor
    relative to the speeds it sees).
    """
    lo, hi = np.log(SCALE_RANGE[0]), np.log(SCALE_RANGE[1])
    k = float(np.exp(rng.uniform(lo, hi)))
    j = float(np.exp(rng.uniform(lo, hi)))
    q = p.replace(
        K_v=p.K_v * k,
        K_T=p.K_T * k,
        K_coulomb=p.K_coulomb * k,
        K_stiction=p.K_stiction * k,
        J_S=p.J_S * j,
    )
    top = p.V_batt / (q.K_v / q.ratio)
    return DrawnTruck(
        params=q,
        k_scale=k,
        j_scale=j,
        rate_hz=float(rng.uniform(50.0, 200.0)),
        jitter=float(rng.uniform(0.0, 0.05)),
        drop=float(rng.uniform(0.0, 0.03)),
        speed_step=float(rng.uniform(0.0, 0.005)) * top,
        noise_v=0.004 * top,
    )


def scaled_effect(name: str, value: float, k_scale: float) -> float:
    """An effect magnitude drawn for the default truck, made equally visible on a truck
    whose motor constant is ``k_scale`` times the default (forces scale with the stall
    force, viscous friction with the back-EMF damping, drag with force per speed^2)."""
    if name == "load_force":
        return value * k_scale
    if name == "viscous_friction":
        return value * k_scale**2
    if name == "aero_drag":
        return value * k_scale**3
    if name == "stribeck":
        return value * k_scale  # a torque, like K_coulomb
    if name == "stribeck_speed":
        return value / k_scale  # the top speed scales as 1/K_v
    return value


def drawn_log(
    truck: DrawnTruck,
    effects: Effects,
    seed: int,
    seconds: float = 50.0,
    with_current: bool = False,
) -> Log:
    """A log of ``truck`` under random excitation: t, u, v (and i, 0.3 A noise)."""
    rng = np.random.default_rng(seed)
    h = 1.0 / truck.rate_hz
    n = int(seconds / h)
    t, u = excitation(rng, n, h=h)
    dt = h * (1.0 + truck.jitter * rng.uniform(-1.0, 1.0, n - 1))
    t = np.concatenate([[0.0], np.cumsum(dt)])
    cfg = PlantConfig(effects=effects, noise_v=truck.noise_v, noise_i=0.3, seed=seed)
    sim = simulate_open_loop(truck.params, t, u, cfg)
    v = sim.v
    if truck.speed_step > 0:
        v = np.round(v / truck.speed_step) * truck.speed_step
    keep = rng.random(n) >= truck.drop
    keep[0] = True
    cols: dict[str, Array] = {"t": t[keep], "u": u[keep], "v": v[keep]}
    if with_current:
        cols["i"] = sim.i[keep]
    name = ", ".join(effects.active()) or "no effect"
    return Log(cols, f"<drawn truck k={truck.k_scale:.3g} J={truck.j_scale:.3g}: {name}>")


def hill_effects(
    truck: DrawnTruck, seed: int, force: float, length: float = 5.0, seconds: float = 50.0
) -> Effects:
    """A hill of ``force`` N on ``length`` m of the road, centred where the clean log of
    ``truck`` (same seed) spends most of its time (so that it is crossed repeatedly)."""
    clean = drawn_log(truck, Effects(), seed, seconds)
    t, v = clean["t"], clean["v"]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    centre = float(np.median(x))
    return Effects(hill_force=force, hill_start=centre - 0.5 * length, hill_length=length)


def hill_force_for(truck: DrawnTruck, p: VehicleParams) -> float:
    """A hill force (N) as visible on ``truck`` as 3 N on the default one, within a 15 %
    grade of the configured weight (a steeper hill stops a weak truck for good)."""
    return min(3.0 * truck.k_scale, 0.15 * p.m * 9.81)


def rolling_effects(truck: DrawnTruck, seed: int, amplitude: float) -> Effects:
    """Rolling terrain of ``amplitude`` N whose wavelength is a quarter of the range the
    clean log of ``truck`` (same seed) drives over (so that it covers several waves)."""
    clean = drawn_log(truck, Effects(), seed)
    t, v = clean["t"], clean["v"]
    x = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    span = float(np.max(x) - np.min(x))
    return Effects(load_force_amplitude=amplitude, load_force_wavelength=max(span / 4.0, 0.5))


def visibility(
    truck: DrawnTruck,
    effects: Effects,
    seed: int,
    seconds: float = 50.0,
    with_current: bool = True,
    base: Effects | None = None,
) -> float:
    """How far hidden ``effects`` move the log of ``truck`` (same seed, no noise) in units
    of its noise: ``sqrt(mean(dv^2)/noise_v^2 + mean(di^2)/(0.3 A)^2)`` (the current's
    term only ``with_current``), from the log with ``base`` hidden (default: none; a
    pair's cause is seen beside the other cause).  Below about 0.3
    the validation cost changes by less than the 5 % a cause must earn: the log cannot
    show it."""
    rng = np.random.default_rng(seed)
    h = 1.0 / truck.rate_hz
    n = int(seconds / h)
    t, u = excitation(rng, n, h=h)
    dt = h * (1.0 + truck.jitter * rng.uniform(-1.0, 1.0, n - 1))
    t = np.concatenate([[0.0], np.cumsum(dt)])
    clean = simulate_open_loop(truck.params, t, u, PlantConfig(effects=base or Effects()))
    hidden = simulate_open_loop(truck.params, t, u, PlantConfig(effects=effects))
    dv = float(np.mean((hidden.v - clean.v) ** 2)) / truck.noise_v**2
    di = float(np.mean((hidden.i - clean.i) ** 2)) / 0.3**2 if with_current else 0.0
    return float(np.sqrt(dv + di))
