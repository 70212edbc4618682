"""The MPC's prediction model is the vehicle model's discretisation (one source of the
physics), and the numpy Riccati solver the daemon uses agrees with scipy's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg

from truckd.control.config import ControlConfig
from truckd.control.qp import (
    I_V,
    ControlModel,
    QpBuilder,
    QpInputs,
    accel_row,
    coordinates,
    prediction_model,
    rel_speed_row,
    stage_weight,
    terminal_weight,
)
from truckd.control.riccati import solve_dare
from truckd.model.effects import Effects
from truckd.model.linear import discretize, state_space
from truckd.model.params import VehicleParams


@pytest.mark.parametrize("viscous", [0.0, 2e-5])
@pytest.mark.parametrize("dt", [0.01, 0.02])
def test_prediction_matrices_are_the_models_discretisation(
    params: VehicleParams, viscous: float, dt: float
) -> None:
    """``Ad``/``bu`` of the MPC, restricted to [R_m i, v], equal ``T Ad T^-1`` / ``T Bd`` of
    :func:`truckd.model.linear.discretize` (the model's own exact ZOH in [i, omega_m])."""
    model = ControlModel(params, Effects(viscous_friction=viscous))
    pred = prediction_model(model, dt)
    ad, bd, _ = discretize(params, dt, viscous)
    t = coordinates(params)
    t_inv = np.linalg.inv(t)
    np.testing.assert_allclose(pred.Ad[:2, :2], t @ ad @ t_inv, rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(pred.bu[:2], (t @ bd)[:, 0], rtol=1e-10, atol=1e-13)
    # The gap integrates the lead's speed minus the truck's: no feedback into the motor.
    np.testing.assert_allclose(pred.Ad[:2, 2], 0.0, atol=0.0)
    assert pred.Ad[2, 2] == 1.0 and pred.bl[2] == pytest.approx(dt, rel=1e-12)
    assert pred.bl[:2] == pytest.approx([0.0, 0.0], abs=0.0)
    # A changed parameter changes the prediction (the model is not a private copy).
    other = prediction_model(ControlModel(params.replace(K_T=params.K_T * 1.1)), dt)
    assert not np.allclose(other.Ad[:2, :2], prediction_model(ControlModel(params), dt).Ad[:2, :2])


@pytest.mark.parametrize("mode", ["follow", "cruise"])
def test_numpy_riccati_equals_scipy(params: VehicleParams, mode: str) -> None:
    cfg = ControlConfig()
    pred = prediction_model(ControlModel(params), cfg.period)
    q = stage_weight(cfg, mode)
    ours = terminal_weight(pred, q, cfg.r_du)
    # The same augmented system, through scipy.
    nx = 3
    a = np.zeros((nx + 1, nx + 1))
    a[:nx, :nx] = pred.Ad
    a[:nx, nx] = pred.bu
    a[nx, nx] = 1.0
    b = np.zeros((nx + 1, 1))
    b[:nx, 0] = pred.bu
    b[nx, 0] = 1.0
    qa = np.zeros((nx + 1, nx + 1))
    qa[:nx, :nx] = q
    keep = [0, 1, 3] if q[2, 2] == 0.0 else [0, 1, 2, 3]
    ix = np.ix_(keep, keep)
    ref = scipy.linalg.solve_discrete_are(a[ix], b[keep], qa[ix], np.array([[cfg.r_du]]))
    np.testing.assert_allclose(ours[ix], ref, rtol=1e-7, atol=1e-9 * np.max(np.abs(ref)))


def test_riccati_on_random_stabilisable_systems() -> None:
    rng = np.random.default_rng(5)
    for _ in range(20):
        n, m = int(rng.integers(2, 6)), int(rng.integers(1, 3))
        a = rng.normal(size=(n, n))
        b = rng.normal(size=(n, m))
        q = np.eye(n) * rng.uniform(0.1, 10.0)
        r = np.eye(m) * rng.uniform(0.1, 10.0)
        x = solve_dare(a, b, q, r)
        ref = scipy.linalg.solve_discrete_are(a, b, q, r)
        np.testing.assert_allclose(x, ref, rtol=1e-6, atol=1e-8 * np.max(np.abs(ref)))


def test_riccati_refuses_an_unstabilisable_pair() -> None:
    a = np.diag([2.0, 0.5])  # the unstable mode gets no input
    b = np.array([[0.0], [1.0]])
    with pytest.raises(ValueError):
        solve_dare(a, b, np.eye(2), np.eye(1))


def test_control_config_replace_still_builds(params: VehicleParams) -> None:
    """Horizons and periods other than the shipped ones build a model too."""
    cfg = dataclasses.replace(ControlConfig(), horizon=10)
    assert prediction_model(ControlModel(params), cfg.period).Ad.shape == (3, 3)


@pytest.mark.parametrize("scale", [0.2, 1.0, 5.0])
def test_the_spacing_rate_row_is_speed_plus_headway_times_acceleration(
    params: VehicleParams, scale: float
) -> None:
    """The follow term with ``rel_speed_lookahead`` h weighs ``v + h dv/dt``: its row on
    the MPC's state, applied to any state, equals the speed plus h times the acceleration
    of the model's own ``[i, omega_m]`` system (the input acts on the current only; trucks
    with 0.2-5x the inertia, viscous friction on); with h = 0 it is the speed alone."""
    p = params.replace(J_S=params.J_S * scale)
    model = ControlModel(p, Effects(viscous_friction=3e-5))
    h = 0.3
    cfg = dataclasses.replace(ControlConfig(), rel_speed_lookahead=h)
    row = rel_speed_row(cfg, accel_row(model))
    ss = state_space(p, 3e-5)  # the model's own [i, omega_m] system, dx/dt = A x + B u
    assert ss.B[1, 0] == 0.0  # the voltage reaches the speed through the current only
    v_per_omega = 1.0 / p.omega(1.0)
    rng = np.random.default_rng(int(scale * 10))
    for _ in range(20):
        x = rng.normal(0.0, [2.0, 1.0, 1.0])  # [R_m i (V), v (m/s), d (m)]
        i_omega = np.array([x[0] / p.R_m, p.omega(x[1])])
        accel = v_per_omega * float((ss.A @ i_omega)[1])  # no input: u = 0
        assert float(row @ x) == pytest.approx(x[I_V] + h * accel, rel=1e-12, abs=1e-12)
    assert list(rel_speed_row(ControlConfig(), accel_row(model))) == [0.0, 1.0, 0.0]
    # The QP weighs it: the follow mode's stage weight is the gap term plus q_rel row row'
    qp = QpBuilder(model, cfg)
    c = np.array([0.0, -cfg.time_headway, 1.0])
    expect = cfg.q_gap * np.outer(c, c) + cfg.q_rel_speed * np.outer(row, row)
    np.testing.assert_allclose(qp.Q["follow"], expect, rtol=1e-12, atol=1e-12)


def test_the_sparse_qp_weighs_the_spacing_error_rate_as_written(params: VehicleParams) -> None:
    """With ``rel_speed_lookahead`` T, the follow QP's objective changes, when the stage
    states of steps 1..N-1 change, as ``sum q_gap (d - d_0 - h v)^2 + q_rel (v + T a -
    v_lead)^2`` does, ``a`` the model's acceleration of each state: the quadratic and the
    linear term built for it (sign and indices), not only its matrix."""
    cfg = dataclasses.replace(ControlConfig(), rel_speed_lookahead=0.3)
    model = ControlModel(params, Effects(viscous_friction=2e-5))
    qp = QpBuilder(model, cfg)
    n, lay = cfg.horizon, qp.lay
    rng = np.random.default_rng(3)
    v_lead = rng.uniform(0.0, 2.0, n)
    inp = QpInputs(np.array([0.5, 1.0, 1.0]), 0.0, v_lead, True, 1.0, 2.4, -7.2, 7.2)
    q, _, _ = qp.vectors("follow", inp)
    p_mat = qp.P["follow"].toarray()
    accel = accel_row(model)

    def objective(z: np.ndarray) -> float:
        return float(0.5 * z @ p_mat @ z + q @ z)

    def stage_cost(z: np.ndarray) -> float:
        total = 0.0
        for k in range(1, n):
            x = z[lay.x(k) : lay.x(k) + 3]
            gap_err = x[2] - cfg.d_0 - cfg.time_headway * x[I_V]
            rate = x[I_V] + cfg.rel_speed_lookahead * float(accel @ x) - v_lead[k]
            total += cfg.q_gap * gap_err**2 + cfg.q_rel_speed * rate**2
        return total

    z1 = rng.normal(size=lay.nz)
    for _ in range(5):
        z2 = z1.copy()
        z2[lay.x(1) : lay.x(n)] = rng.normal(size=lay.x(n) - lay.x(1))  # stage states only
        assert objective(z2) - objective(z1) == pytest.approx(
            stage_cost(z2) - stage_cost(z1), rel=1e-9, abs=1e-9
        )
