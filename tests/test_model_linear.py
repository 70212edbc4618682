"""The closed-form 2x2 exponential and the exact ZOH against scipy's references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from truckd.model.linear import discretize, expm, expm2, state_space, zoh
from truckd.model.params import VehicleParams

finite = st.floats(-50.0, 50.0, allow_nan=False)


@given(a00=finite, a01=finite, a10=finite, a11=finite, t=st.floats(1e-4, 0.5))
@settings(max_examples=300, deadline=None)
def test_expm2_matches_scipy(a00: float, a01: float, a10: float, a11: float, t: float) -> None:
    """Real, complex and repeated eigenvalues alike."""
    ref = scipy.linalg.expm(np.array([[a00, a01], [a10, a11]]) * t)
    got = np.array(expm2((a00, a01, a10, a11), t)).reshape(2, 2)
    assert np.allclose(got, ref, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(ref).max()))


def test_expm2_stiff_matrix_does_not_overflow(params: VehicleParams) -> None:
    """The motor's fast pole (-R/L ~ -2000/s) over a long step: no inf/nan, matches scipy."""
    ss = state_space(params)
    for t in (1e-5, 0.01, 1.0, 10.0):
        a = ss.A
        got = np.array(expm2((a[0, 0], a[0, 1], a[1, 0], a[1, 1]), t)).reshape(2, 2)
        assert np.all(np.isfinite(got))
        assert np.allclose(got, scipy.linalg.expm(a * t), rtol=1e-8, atol=1e-12)


@pytest.mark.parametrize("h", [1e-4, 0.01, 0.05])
def test_zoh_matches_scipy_cont2discrete(params: VehicleParams, h: float) -> None:
    ss = state_space(params, viscous=1e-6)
    ad, bd = zoh(ss.A, np.hstack([ss.B, ss.E]), h)
    ref = scipy.signal.cont2discrete(
        (ss.A, np.hstack([ss.B, ss.E]), ss.C, np.zeros((1, 2))), h, method="zoh"
    )
    assert np.allclose(ad, ref[0], rtol=1e-9, atol=1e-12)
    assert np.allclose(bd, ref[1], rtol=1e-9, atol=1e-15)
    ad2, bv, et = discretize(params, h, viscous=1e-6)
    assert np.allclose(ad2, ad) and np.allclose(bv, bd[:, :1]) and np.allclose(et, bd[:, 1:])


def test_numpy_expm_matches_scipy_on_larger_matrix() -> None:
    rng = np.random.default_rng(1)
    m = rng.normal(size=(5, 5)) * 3.0
    assert np.allclose(expm(m), scipy.linalg.expm(m), rtol=1e-10, atol=1e-10)


def test_state_space_output_is_vehicle_speed(params: VehicleParams) -> None:
    ss = state_space(params)
    omega = 1000.0
    assert ss.C @ np.array([0.0, omega]) == pytest.approx(
        params.r_w * omega / (params.n_g * params.n_fd)
    )
    # The electrical pole is faster than 1 ms, the mechanical slower than 10 ms.
    poles = np.sort(np.linalg.eigvals(ss.A).real)
    assert poles[0] < -1000.0 and -100.0 < poles[1] < 0.0
