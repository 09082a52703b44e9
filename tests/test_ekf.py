"""Tests of kftrack.ekf: the EKF on a linear model is the Kalman filter bit for bit; angle
wrapping across +-pi; the linearized transform; the Monte Carlo simulator by chi-square
bounds; bad input."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from kftrack import ekf, kalman
from kftrack.kernels import mv as _mv


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + n * np.eye(n))


def linear(F, H):
    """The linear model as EKF callables (f, F_jac, h, H_jac), broadcasting."""
    n, m = F.shape[0], H.shape[0]
    return (lambda x: _mv(F, x), lambda x: np.broadcast_to(F, x.shape[:-1] + (n, n)),
            lambda x: _mv(H, x), lambda x: np.broadcast_to(H, x.shape[:-1] + (m, n)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ekf_on_linear_model_is_kalman_filter_exactly(seed):
    rng = np.random.default_rng(seed)
    n, m, T, N = 4, 2, 25, 6
    F = np.eye(n) + 0.2 * rng.normal(size=(n, n))
    Q, H, R = random_spd(rng, n, 0.1), rng.normal(size=(m, n)), random_spd(rng, m)
    x0, P0 = rng.normal(size=n), random_spd(rng, n)
    f, Fj, h, Hj = linear(F, H)
    _, zs = ekf.simulate_additive_gaussian(f, h, x0, P0, Q, R, T, rng, runs=N)
    zs[4, 1] = np.nan  # one missing measurement in one run
    zs[7] = np.nan  # a step without any measurement
    kf = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    ek = ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, h, Hj, R)
    for name, a, b in zip(kf._fields, kf, ek):
        assert np.array_equal(a, b, equal_nan=True), name


def test_single_steps_equal_kalman_exactly():
    rng = np.random.default_rng(5)
    n, m = 3, 2
    F, H = rng.normal(size=(n, n)), rng.normal(size=(m, n))
    Q, R = random_spd(rng, n), random_spd(rng, m)
    x, P, z = rng.normal(size=(7, n)), random_spd(rng, n), rng.normal(size=(7, m))
    f, Fj, h, Hj = linear(F, H)
    # the Jacobian callables return one matrix per batch member, so compare broadcast values
    for a, b in zip(kalman.predict(x, P, F, Q), ekf.ekf_predict(x, P, f, Fj, Q)):
        assert np.array_equal(np.broadcast_to(a, b.shape), b)
    for a, b in zip(kalman.update(x, P, z, H, R), ekf.ekf_update(x, P, z, h, Hj, R)):
        assert np.array_equal(np.broadcast_to(a, b.shape), b)


def test_progress_bar_does_not_change_the_result():
    rng = np.random.default_rng(3)
    F, H = np.eye(2), np.eye(2)
    f, Fj, h, Hj = linear(F, H)
    zs = rng.normal(size=(5, 2))
    a = ekf.extended_kalman_filter(zs, np.zeros(2), np.eye(2), f, Fj, np.eye(2), h, Hj, np.eye(2))
    b = ekf.extended_kalman_filter(zs, np.zeros(2), np.eye(2), f, Fj, np.eye(2), h, Hj, np.eye(2), progress=True)
    assert all(np.array_equal(u, v) for u, v in zip(a, b))


# --- angles ----------------------------------------------------------------------------


def test_wrap_angle_exact_values():
    pi = np.pi
    got = ekf.wrap_angle([0.0, pi, -pi, 3 * pi, -3 * pi, 2 * pi, pi / 2, -pi / 2 - 2 * pi])
    assert np.allclose(got, [0, pi, pi, pi, pi, 0, pi / 2, -pi / 2], atol=1e-15, rtol=0)
    assert ekf.wrap_angle(pi) == pi and ekf.wrap_angle(-pi) == pi


@settings(max_examples=200, deadline=None)
@given(a=st.floats(-1e4, 1e4))
def test_wrap_angle_range_and_equivalence(a):
    w = float(ekf.wrap_angle(a))
    assert -np.pi < w <= np.pi
    k = (a - w) / (2 * np.pi)
    assert abs(k - round(k)) < 1e-9 * max(1.0, abs(a))


def test_residual_across_pi():
    d = np.deg2rad
    y = ekf.residual([10.0, d(179.0)], [9.0, d(-179.0)], angle_components=[1])
    assert np.allclose(y, [1.0, d(-2.0)], atol=1e-12)
    # without the angle component it is the plain difference
    assert np.isclose(ekf.residual([0.0, d(179.0)], [0.0, d(-179.0)])[1], d(358.0))


def test_state_angle_is_wrapped_in_prediction_and_update():
    """A heading state with a constant rate, measured directly: wrapping the state and the
    innovation gives the linear Kalman filter on the unwrapped angles, wrapped afterwards, to
    round-off, with every predicted and filtered heading in (-pi, pi]."""
    rng = np.random.default_rng(4)
    F, H = np.array([[1.0, 1.0], [0.0, 1.0]]), np.array([[1.0, 0.0]])  # state [theta, omega]
    Q, R = np.diag([1e-4, 1e-5]), np.array([[0.05**2]])
    x0, P0 = np.array([2.5, 0.3]), np.diag([0.1**2, 0.05**2])
    f, Fj, h, Hj = linear(F, H)
    truth, _ = ekf.simulate_additive_gaussian(f, h, x0, P0, Q, R, 40, rng, runs=8)  # theta grows to ~14 rad
    z_unwrapped = truth[..., :1] + 0.05 * rng.standard_normal(truth.shape[:-1] + (1,))
    ref = kalman.kalman_filter(z_unwrapped, x0, P0, F, Q, H, R)
    out = ekf.extended_kalman_filter(ekf.wrap_angle(z_unwrapped), x0, P0, lambda x: ekf.wrap_angle(f(x)), Fj, Q,
                                     lambda x: ekf.wrap_angle(h(x)), Hj, R, angle_components=[0], state_angles=[0])
    for name in ("x", "x_prior"):
        theta = getattr(out, name)[..., 0]
        assert np.all((theta > -np.pi) & (theta <= np.pi)), name
        d = ekf.wrap_angle(theta - getattr(ref, name)[..., 0])
        assert np.max(np.abs(d)) < 1e-12, name
        np.testing.assert_allclose(getattr(out, name)[..., 1], getattr(ref, name)[..., 1], rtol=0, atol=1e-13)
    assert np.array_equal(out.P, ref.P) and np.array_equal(out.P_prior, ref.P_prior)
    np.testing.assert_allclose(out.nis, ref.nis, rtol=1e-9)
    assert np.abs(ref.x[..., 0]).max() > 3 * np.pi  # the test crosses the cut several times
    # single steps: the posterior crosses the cut
    u = ekf.ekf_update([np.pi - 0.01, 0.0], np.diag([0.01, 1.0]), [-np.pi + 0.01], h, Hj, [[1e-4]],
                       angle_components=[0], state_angles=[0])
    assert u.x[0] == pytest.approx(np.pi - 0.01 + 0.01 / (0.01 + 1e-4) * 0.02 - 2 * np.pi, abs=1e-12)
    xp, _ = ekf.ekf_predict([np.pi - 0.1, 0.3], P0, f, Fj, Q, state_angles=[0])
    assert xp[0] == pytest.approx(np.pi + 0.2 - 2 * np.pi, abs=1e-15)


# --- linearized transform -------------------------------------------------------------


def test_linearized_transform_is_exact_for_affine_maps():
    rng = np.random.default_rng(2)
    A, b = rng.normal(size=(3, 4)), rng.normal(size=3)
    x, P = rng.normal(size=4), random_spd(rng, 4)
    mean, cov = ekf.linearized_transform(lambda v: v @ A.T + b, lambda v: np.broadcast_to(A, v.shape[:-1] + A.shape), x, P)
    assert np.allclose(mean, A @ x + b, rtol=1e-14)
    assert np.allclose(cov, A @ P @ A.T, rtol=1e-13)


# --- simulator ---------------------------------------------------------------------------


def test_simulated_measurement_noise_is_chi_square():
    rng = np.random.default_rng(11)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = 0.5 * np.array([[0.25, 0.5], [0.5, 1.0]])  # rank 1: singular Q must work
    H = np.array([[1.0, 0.0]])
    R = np.array([[4.0]])
    f, _, h, _ = linear(F, H)
    truth, zs = ekf.simulate_additive_gaussian(f, h, [0.0, 1.0], np.eye(2), Q, R, 50, rng, runs=40)
    assert truth.shape == (50, 40, 2) and zs.shape == (50, 40, 1)
    e = (zs - truth[..., :1])[..., 0]
    total = np.sum(e**2 / 4.0)
    dof = e.size
    assert stats.chi2.ppf(0.0005, dof) < total < stats.chi2.ppf(0.9995, dof)
    # process noise along its single direction only: w = x_{k+1} - F x_k is parallel to [1/2, 1]
    w = truth[1:] - truth[:-1] @ F.T
    assert np.allclose(w[..., 0], 0.5 * w[..., 1], atol=1e-12)
    one, _ = ekf.simulate_additive_gaussian(f, h, [0.0, 1.0], np.eye(2), Q, R, 3, np.random.default_rng(0))
    assert one.shape == (3, 2)


# --- bad input --------------------------------------------------------------------------


def test_bad_input_names_the_argument():
    F, H = np.eye(2), np.eye(2)
    f, Fj, h, Hj = linear(F, H)
    x, P, z = np.zeros(2), np.eye(2), np.zeros(2)
    with pytest.raises(ValueError, match=r"^h\(x\) must"):
        ekf.ekf_update(x, P, z, lambda v: v[..., :1], Hj, np.eye(2))
    with pytest.raises(ValueError, match="H_jac"):
        ekf.ekf_update(x, P, z, h, lambda v: np.zeros(v.shape[:-1] + (2, 3)), np.eye(2))
    with pytest.raises(ValueError, match="angle_components"):
        ekf.ekf_update(x, P, z, h, Hj, np.eye(2), angle_components=[5])
    with pytest.raises(TypeError, match="angle_components"):
        ekf.residual(z, z, angle_components=1)
    with pytest.raises(ValueError, match="F_jac"):
        ekf.ekf_predict(x, P, f, lambda v: np.eye(3), np.eye(2))
    with pytest.raises(ValueError, match="state_angles"):
        ekf.ekf_predict(x, P, f, Fj, np.eye(2), state_angles=[2])
    with pytest.raises(ValueError, match="state_angles"):
        ekf.extended_kalman_filter(np.zeros((3, 2)), x, P, f, Fj, np.eye(2), h, Hj, np.eye(2), state_angles=[-3])
    with pytest.raises(ValueError, match=r"^Q must"):
        ekf.ekf_predict(x, P, f, Fj, -np.eye(2))
    with pytest.raises(ValueError, match=r"^R must"):
        ekf.ekf_update(x, P, z, h, Hj, np.zeros((2, 2)))
    with pytest.raises(ValueError, match="zs"):
        ekf.extended_kalman_filter(np.zeros(3), x, P, f, Fj, np.eye(2), h, Hj, np.eye(2))
    with pytest.raises(ValueError, match="partly NaN"):
        ekf.extended_kalman_filter(np.array([[0.0, np.nan]]), x, P, f, Fj, np.eye(2), h, Hj, np.eye(2))
    with pytest.raises(TypeError, match="rng"):
        ekf.simulate_additive_gaussian(f, h, x, P, np.eye(2), np.eye(2), 3, rng=0)
    with pytest.raises(ValueError, match="steps"):
        ekf.simulate_additive_gaussian(f, h, x, P, np.eye(2), np.eye(2), 0, np.random.default_rng(0))


def test_linear_measurement_matrix_is_the_kalman_update_exactly():
    rng = np.random.default_rng(11)
    n, m, N = 4, 2, 5
    H, R = rng.normal(size=(m, n)), random_spd(rng, m)
    x, P, z = rng.normal(size=(N, n)), random_spd(rng, n), rng.normal(size=(N, m))
    ref = kalman.update(x, P, z, H, R)
    u = ekf.ekf_update(x, P, z, H, None, R)  # h given as the (m, n) matrix H, H_jac None
    for name, a, b in zip(ref._fields, ref, u):
        assert np.array_equal(a, np.broadcast_to(b, np.shape(a))), name
    # the whole-sequence filter too
    F = np.eye(n) + 0.2 * rng.normal(size=(n, n))
    Q, x0, P0 = random_spd(rng, n, 0.1), rng.normal(size=n), random_spd(rng, n)
    f, Fj, h, _ = linear(F, H)
    _, zs = ekf.simulate_additive_gaussian(f, h, x0, P0, Q, R, 12, rng, runs=N)
    kf = kalman.kalman_filter(zs, x0, P0, F, Q, H, R)
    ek = ekf.extended_kalman_filter(zs, x0, P0, f, Fj, Q, H, None, R)
    for name, a, b in zip(kf._fields, kf, ek):
        assert np.array_equal(a, b, equal_nan=True), name


def test_linear_measurement_matrix_bad_input():
    rng = np.random.default_rng(12)
    H, R, x, P, z = rng.normal(size=(2, 4)), np.eye(2), np.zeros(4), np.eye(4), np.zeros(2)
    with pytest.raises(ValueError, match="H_jac must be None when h is a matrix"):
        ekf.ekf_update(x, P, z, H, lambda s: H, R)
    with pytest.raises(ValueError, match=r"h must have shape \(\.\.\., 2, 4\)"):
        ekf.ekf_update(x, P, z, H[:, :3], None, R)
    with pytest.raises(ValueError, match="H_jac must be a callable"):
        ekf.ekf_update(x, P, z, lambda s: _mv(H, s), None, R)
    with pytest.raises(ValueError, match="h as a linear measurement matrix must have shape"):
        ekf.ekf_update(x, P, z, np.stack([H, H]), None, R)
