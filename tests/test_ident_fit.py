"""Seed identification, log checks and residual statistics."""

from __future__ import annotations

import numpy as np
import pytest
from labkit.synth import plant_log

from truckd.errors import InputError
from truckd.ident.api import identify_log
from truckd.ident.data import series_from_log
from truckd.ident.residuals import (
    FFT_LEN,
    autocorr,
    band,
    binned,
    crosscorr,
    lagged_sums,
    whiteness,
)
from truckd.ident.voltage import speed_fit
from truckd.logfile import Log
from truckd.model.effects import Effects
from truckd.model.params import VehicleParams


def _truth(params: VehicleParams) -> VehicleParams:
    """A truck that differs from the configuration (the fit must move away from it)."""
    return params.replace(
        K_v=params.K_v * 1.12,
        K_T=params.K_T * 1.12,
        J_S=params.J_S * 0.8,
        K_coulomb=params.K_coulomb * 1.3,
        K_stiction=params.K_coulomb * 1.3 * 1.5,
        R_m=params.R_m * 1.2,
    )


def test_identify_recovers_seed_parameters_with_current(params: VehicleParams) -> None:
    true = _truth(params)
    log = plant_log(true, Effects(), seed=31, n=5000)
    model = identify_log(log, params).vehicle
    assert model.K_v == pytest.approx(true.K_v, rel=0.02)
    assert model.R_m == pytest.approx(true.R_m, rel=0.05)
    assert model.J_S == pytest.approx(true.J_S, rel=0.05)
    assert model.K_coulomb == pytest.approx(true.K_coulomb, rel=0.05)
    assert model.L_m == params.L_m  # not identifiable: left at the configured value
    # The breakaway torque is only determined to between the command levels that did
    # and did not break the truck away: swapping in the true value must not fit better.
    data = series_from_log(log)
    found = speed_fit(model, Effects(), data)[1]
    with_true = speed_fit(model.replace(K_stiction=true.K_stiction), Effects(), data)[1]
    assert found <= with_true * 1.01
    assert model.K_stiction >= model.K_coulomb


def test_identify_speed_only_determines_the_ratios(params: VehicleParams) -> None:
    """Without current R_m stays configured; K_v and J_S R/K_T, K_c R/K_T are found."""
    true = _truth(params)
    log = plant_log(true, Effects(), seed=32, n=5000, with_current=False)
    m = identify_log(log, params).vehicle
    assert m.R_m == params.R_m
    assert m.K_v == pytest.approx(true.K_v, rel=0.02)

    def group(p: VehicleParams, x: float) -> float:
        return x * p.R_m / p.K_T

    assert group(m, m.J_S) == pytest.approx(group(true, true.J_S), rel=0.05)
    assert group(m, m.K_coulomb) == pytest.approx(group(true, true.K_coulomb), rel=0.05)


def _log(**cols: np.ndarray) -> Log:
    return Log(dict(cols), "bad.csv")


def test_too_short_log_is_refused(params: VehicleParams) -> None:
    t = np.arange(30) * 0.01
    with pytest.raises(InputError, match=r"bad.csv: only 30 samples"):
        identify_log(_log(t=t, u=np.sin(t), v=np.sin(t)), params)


def test_zero_input_is_refused(params: VehicleParams) -> None:
    """Motion with 0 V throughout (pushed by hand) determines nothing of the drive."""
    t = np.arange(1000) * 0.01
    with pytest.raises(InputError, match=r"bad.csv: column 'u' is 0 throughout"):
        identify_log(_log(t=t, u=np.zeros_like(t), v=np.linspace(0, 1, 1000)), params)


def test_no_motion_is_refused(params: VehicleParams) -> None:
    t = np.arange(1000) * 0.01
    u = 0.3 * np.sin(t)
    with pytest.raises(InputError, match=r"no motion"):
        identify_log(_log(t=t, u=u, v=np.zeros_like(t)), params)


def test_force_log_is_refused_by_identify(params: VehicleParams) -> None:
    t = np.arange(1000) * 0.01
    with pytest.raises(InputError, match=r"needs column 'u'"):
        identify_log(_log(t=t, F=np.sin(t), x=np.cos(t)), params)


def test_force_log_speed_from_position() -> None:
    t = np.arange(2000) * 0.001
    x = 0.1 * np.sin(2 * np.pi * t)
    s = series_from_log(_log(t=t, F=np.cos(3 * t) + t, x=x))
    core = slice(100, -100)
    assert np.max(np.abs(s.v[core] - 0.2 * np.pi * np.cos(2 * np.pi * t[core]))) < 1e-3


def test_white_noise_stays_in_the_band() -> None:
    rng = np.random.default_rng(0)
    r = rng.normal(size=20000)
    acf = autocorr(r, 50)
    assert acf[0] == pytest.approx(1.0)
    assert np.mean(np.abs(acf[1:]) > band(len(r))) < 0.05
    w = whiteness(r, rng.normal(size=20000), 1.0, 50)
    assert w.acf_outside < 0.05 and w.ccf_outside < 0.05
    assert w.structure < 0.05


def test_structure_leaves_the_band() -> None:
    t = np.arange(5000) * 0.01
    r = np.sin(2 * np.pi * 0.3 * t) + np.random.default_rng(1).normal(scale=0.3, size=5000)
    w = whiteness(r, np.zeros(5000) + np.arange(5000) % 7, 0.3, 100)
    assert w.acf_outside > 0.5
    assert w.structure > 0.6


def test_crosscorrelation_finds_the_lag() -> None:
    rng = np.random.default_rng(2)
    u = rng.normal(size=5000)
    r = np.roll(u, 7)  # r[k] = u[k-7]
    c = crosscorr(r, u, 20)
    assert int(np.argmax(c)) - 20 == 7
    assert c.max() == pytest.approx(1.0, abs=0.01)


@pytest.mark.parametrize(
    ("n", "lags"), [(1, 0), (9, 3), (2000, 40), (FFT_LEN - 80, 40), (3 * FFT_LEN + 17, 250)]
)
def test_lagged_sums_are_the_direct_sums_whatever_the_length(n: int, lags: int) -> None:
    """A long record is summed in blocks (memory that does not grow with it): every lag's
    sum is the direct one, across the blocks' edges and at the record's ends."""
    rng = np.random.default_rng(n)
    a, b = rng.normal(size=n).cumsum(), rng.normal(size=n)
    direct = [
        float(a[max(0, lag) : n + min(0, lag)] @ b[max(0, -lag) : n - max(0, lag)])
        for lag in range(-lags, lags + 1)
    ]
    assert np.allclose(lagged_sums(a, b, lags), direct, rtol=1e-9, atol=1e-9 * n)


def test_binned_residual_shows_a_dependence() -> None:
    x = np.linspace(-1, 1, 2000)
    b = binned(x, 0.5 * x, bins=10)
    assert np.all(np.diff(b.mean) > 0)
    assert np.allclose(b.mean, 0.5 * b.centers, atol=1e-9)
