"""The C free-run kernel gives the Python loop's speeds (the reference), bit for bit
or nearly, over trucks, rates and every effect the kernel models."""

from __future__ import annotations

import numpy as np
import pytest
from labkit.synth import draw_truck, plant_log

from truckd.config.truck import load_config
from truckd.ident import ckernel, fastsim, freerun
from truckd.model.effects import Effects

EFFECTS = [
    Effects(),
    Effects(sensor_lag=0.06),
    Effects(input_delay=0.027),
    Effects(battery_sag=0.2, aero_drag=0.8),
    Effects(dead_zone=1.2, voltage_saturation=5.0, load_force=2.0),
    Effects(load_force_amplitude=2.0, load_force_wavelength=1.7, load_force_phase=0.3),
    Effects(hill_force=3.0, hill_start=0.5, hill_length=2.0, viscous_friction=5e-5),
    Effects(stribeck=0.012, stribeck_speed=0.1, input_delay=0.013),
    Effects(current_limit=25.0, viscous_friction=5e-5, sensor_lag=0.03),
    Effects(current_limit=5.0, stribeck=0.008, stribeck_speed=0.2, battery_sag=0.2),
    Effects(resistance_drift=1.2, winding_time_constant=15.0, aero_drag=0.5),
    Effects(
        resistance_drift=3.0,
        winding_time_constant=3.0,
        stribeck=0.01,
        stribeck_speed=0.1,
        load_force_amplitude=1.0,
        load_force_wavelength=1.3,
        input_delay=0.012,
    ),
    Effects(backlash=0.4, rotor_inertia_fraction=0.3),
    Effects(backlash=0.3, current_limit=5.0, stribeck=0.01, stribeck_speed=0.1, sensor_lag=0.02),
    Effects(
        backlash=0.4,
        rotor_inertia_fraction=0.3,
        resistance_drift=3.0,
        winding_time_constant=3.0,
        current_limit=8.0,
        battery_sag=0.2,
        input_delay=0.012,
    ),
]


def test_the_kernel_is_built() -> None:
    assert ckernel.available(), f"{ckernel.LIBRARY} missing: run `make firmware`"


@pytest.mark.parametrize("k", range(len(EFFECTS)))
def test_kernel_matches_the_python_loop(k: int, monkeypatch: pytest.MonkeyPatch) -> None:
    p0 = load_config().vehicle
    rng = np.random.default_rng(100 + k)
    p = draw_truck(p0, rng).params
    eff = EFFECTS[k]
    log = plant_log(p, eff, seed=k, n=2000)
    t, u = log.columns["t"], log.columns["u"]
    with monkeypatch.context() as m:
        # the kernel runs it all: the Python loop would fail
        m.setattr(freerun, "_run_in_python", None)
        fast = fastsim.simulate_voltage(p, eff, t, u, 0.1, x0=0.2)
    orig = fastsim.run

    def python_only(*a: object, **kw: object) -> object:
        return orig(*a, use_kernel=False, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(fastsim, "run", python_only)
    monkeypatch.setattr(ckernel, "winding_rises", lambda *a: None)
    # A resistance drift: the kernel steps the winding beside the speed in one run; the
    # reference is the Python passes, converged far below the shipped tolerance.
    monkeypatch.setattr(ckernel, "available", lambda: False)
    monkeypatch.setattr(fastsim, "DRIFT_TOLERANCE", 1e-14)
    ref = fastsim.simulate_voltage(p, eff, t, u, 0.1, x0=0.2)
    scale = float(np.max(np.abs(ref.v)))
    assert scale > 0.0
    assert np.max(np.abs(fast.v - ref.v)) <= 1e-9 * scale
    assert np.max(np.abs(fast.x - ref.x)) <= 1e-9 * max(float(np.max(np.abs(ref.x))), 1.0)


def test_the_kernel_version_is_checked() -> None:
    """The library's version is the one the source declares and the loader expects; a
    library without it (built before versions) or of another version is refused."""
    import ctypes
    import re

    src = (ckernel.LIBRARY.parents[1] / "fastrun.c").read_text()
    declared = re.search(r"#define TRUCKD_FASTRUN_ABI (\d+)", src)
    assert declared is not None and int(declared.group(1)) == ckernel.ABI
    lib = ckernel.library()
    assert lib is not None and ckernel._current(lib)

    class Stale:
        """A library without the version function."""

    assert not ckernel._current(Stale())  # type: ignore[arg-type]
    other = ctypes.CDLL(str(ckernel.LIBRARY))
    saved = ckernel.ABI
    try:
        ckernel.ABI = saved + 1
        assert not ckernel._current(other)
    finally:
        ckernel.ABI = saved
