"""Tests of the pieces chapter 7 adds for seed 001's 3-D turn EKF: state-dependent process
noise and per-step measurement covariances in ``ekf.extended_kalman_filter`` (exactly the
step-by-step recursion), ``Turn3DAngles.state_from_motion``, and the paper's partial
Jacobian freezing the turn rates (exactly) where the full Jacobian learns them."""
from __future__ import annotations

import numpy as np
import pytest

from kftrack import ekf, kalman, scenarios
from kftrack.models import ConstantVelocity, Turn3DAngles
from kftrack.sensors import radar as rd
from test_ekf import linear, random_spd  # the linear model as EKF callables; random SPD matrices


@pytest.fixture
def linear_case():
    """A 2-D constant-velocity model seen through a random mixing of its state (20 steps, 5 runs)."""
    rng = np.random.default_rng(11)
    cv = ConstantVelocity(ndim=2, q=0.5)
    F, Q, H, R = cv.F(1.0), cv.Q(1.0), rng.normal(size=(2, 4)), random_spd(rng, 2)
    x0, P0 = np.array([0.0, 1.0, 0.0, -1.0]), random_spd(rng, 4)
    _, zs = ekf.simulate_additive_gaussian(*linear(F, H)[::2], x0, P0, Q, R, 20, rng, runs=5)
    return rng, F, Q, H, R, x0, P0, zs


def test_constant_callable_Q_and_repeated_R_are_the_fixed_filter_exactly(linear_case):
    rng, F, Q, H, R, x0, P0, zs = linear_case
    f, Fj, h, Hj = linear(F, H)
    zs[6, 2] = np.nan  # one missing measurement
    ref = ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, R)
    Rs = np.broadcast_to(R, zs.shape[:-1] + R.shape).copy()
    Rs[6, 2] = np.nan  # a missing step may carry an undefined covariance
    for out in (ekf.extended_kalman_filter(zs, x0, P0, f, Fj, lambda x: np.broadcast_to(Q, x.shape[:-1] + Q.shape),
                                           h, Hj, R),
                ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, Rs, R_per_step=True)):
        for a, b in zip(ref, out):
            assert np.array_equal(a, b, equal_nan=True)


def test_state_dependent_Q_and_per_step_R_equal_the_step_by_step_recursion(linear_case):
    rng, F, Q, H, R, x0, P0, zs = linear_case
    f, Fj, h, Hj = linear(F, H)
    T, N = zs.shape[:2]
    Rs = np.stack([random_spd(rng, 2) for _ in range(T * N)]).reshape(T, N, 2, 2)

    def Qx(x):  # grows with the state: a stand-in for seed 001's Gamma(x) Sigma Gamma(x)^T
        return Q * (1.0 + np.sum(x**2, axis=-1))[..., None, None]

    out = ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Qx, h, Hj, Rs, R_per_step=True)
    x, P = np.broadcast_to(x0, (N, 4)), np.broadcast_to(P0, (N, 4, 4))
    for k in range(T):
        np.testing.assert_array_equal(out.x_prior[k], x)
        u = kalman.update(x, P, zs[k], H, Rs[k])
        np.testing.assert_allclose(out.x[k], u.x, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out.P[k], u.P, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(out.nis[k], u.nis, rtol=1e-12)
        x, P = out.x[k], out.P[k]
        x, P = kalman.predict(x, P, F, Qx(x))


def test_per_step_R_is_used_at_its_own_step(linear_case):
    """A huge R at one step makes that measurement worthless: the update barely moves."""
    rng, F, Q, H, R, x0, P0, zs = linear_case
    f, Fj, h, Hj = linear(F, H)
    Rs = np.broadcast_to(R, zs.shape[:-1] + R.shape).copy()
    Rs[5] = 1e12 * np.eye(2)
    out = ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, Rs, R_per_step=True)
    np.testing.assert_allclose(out.x[5], out.x_prior[5], rtol=1e-8, atol=1e-8)
    assert np.abs(out.x[4] - out.x_prior[4]).max() > 1e-3


def test_state_from_motion_recovers_the_rates_of_the_exact_model():
    x = np.array([[100.0, 200.0, -50.0, 100.0, 900.0, 50.0, 0.03, -0.02],
                  [0.0, -150.0, 10.0, -20.0, 0.0, -30.0, -0.05, 0.01]])
    d = 1e-3
    v = lambda s: s[..., [1, 3, 5]]  # noqa: E731
    a = (v(Turn3DAngles.f_exact(x, d)) - v(Turn3DAngles.f_exact(x, -d))) / (2 * d)
    out = Turn3DAngles.state_from_motion(x[:, [0, 2, 4]], v(x), a)
    np.testing.assert_allclose(out[:, :6], x[:, :6], rtol=0, atol=0)
    np.testing.assert_allclose(out[:, 6:], x[:, 6:], rtol=1e-6)


def test_state_from_motion_on_the_tilted_zigzag():
    z = scenarios.tilted_zigzag(np.random.default_rng(0))
    X = Turn3DAngles.state_from_motion(z.track.r, z.track.v, z.track.a)
    np.testing.assert_array_equal(X[:, :6], z.truth)
    straight = z.label == 0
    np.testing.assert_allclose(X[straight, 6:], 0.0, atol=1e-12)
    # in a turn the total rate equals the turn rate: omega^2 = (cos(gamma) omega_chi)^2 + omega_gamma^2
    gam = np.arctan2(X[:, 5], np.hypot(X[:, 1], X[:, 3]))
    turn = z.label == 1
    np.testing.assert_allclose(np.hypot(np.cos(gam) * X[:, 6], X[:, 7])[turn], 0.05, rtol=1e-9)


def _zigzag_filters(jacobian: str, runs: int = 20):
    rng = np.random.default_rng(3)
    z = scenarios.tilted_zigzag(rng)
    truth = np.broadcast_to(z.truth[:, None], (len(z.t), runs, 6))
    radar = rd.RangeAzimuthElevation(sigmas=(75.0, 3e-4, 3e-4))
    zs = radar.simulate(truth, rng)
    conv = radar.to_cartesian(zs, "debiased")
    x6, P6 = rd.three_point_state(conv.p[:3], conv.C[:3], dt=4.0)
    x0 = np.concatenate([x6, np.zeros((runs, 2))], axis=-1)
    P0 = np.zeros((runs, 8, 8))
    P0[:, :6, :6], P0[:, 6, 6], P0[:, 7, 7] = P6, 0.05**2, 0.05**2
    m = Turn3DAngles(sigma2=1.0, sigma2_omega=1e-4)
    J = m.F if jacobian == "partial" else m.jacobian
    return ekf.extended_kalman_filter(zs[2:], x0, P0, lambda x: m.f(x, 4.0), lambda x: J(x, 4.0),
                                      lambda x: m.Q(x, 4.0), radar.h, radar.jacobian, radar.R,
                                      radar.angle_components), z


def test_partial_jacobian_freezes_the_turn_rates_exactly_and_the_full_one_learns_them():
    partial, z = _zigzag_filters("partial")
    assert np.all(partial.x[..., 6:] == 0.0)
    assert np.all(partial.P[..., 6:, :6] == 0.0)  # no cross-covariance ever appears
    full, _ = _zigzag_filters("full")
    turning = z.label[2:] == 1
    w = full.x[..., 6].mean(axis=1)
    truth_w = Turn3DAngles.state_from_motion(z.track.r, z.track.v, z.track.a)[2:, 6]
    # over the turns the full-Jacobian estimate follows the true heading rate
    assert np.corrcoef(w[turning], truth_w[turning])[0, 1] > 0.8
    err = lambda r: np.sqrt(np.mean(np.sum((r.x[..., [0, 2, 4]] - z.truth[2:, None, [0, 2, 4]]) ** 2, -1)))  # noqa: E731
    assert err(full) < err(partial)


def test_bad_input_names_the_argument(linear_case):
    rng, F, Q, H, R, x0, P0, zs = linear_case
    f, Fj, h, Hj = linear(F, H)
    with pytest.raises(ValueError, match=r"^Q\(x\) must"):
        ekf.extended_kalman_filter(zs, x0, P0, f, Fj, lambda x: np.eye(3), h, Hj, R)
    with pytest.raises(ValueError, match=r"^Q must"):
        ekf.extended_kalman_filter(zs, x0, P0, f, Fj, lambda x: -np.broadcast_to(Q, x.shape[:-1] + Q.shape), h, Hj, R)
    with pytest.raises(ValueError, match=r"^R must"):
        ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, R, R_per_step=True)  # no time axis
    with pytest.raises(ValueError, match=r"^R must"):
        ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, np.broadcast_to(R, (3,) + zs.shape[1:-1] + R.shape),
                                   R_per_step=True)
    with pytest.raises(ValueError, match=r"^R must"):
        ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, -np.broadcast_to(R, zs.shape[:-1] + R.shape),
                                   R_per_step=True)
    with pytest.raises(ValueError, match=r"^v must"):
        Turn3DAngles.state_from_motion(np.zeros(3), [0.0, 0.0, 10.0], np.zeros(3))
    with pytest.raises(ValueError, match=r"^a must"):
        Turn3DAngles.state_from_motion(np.zeros(3), [1.0, 0.0, 0.0], np.zeros(2))
